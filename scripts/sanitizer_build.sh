#!/usr/bin/env bash
# Configures build-fuzz/ (clang, AddressSanitizer + UBSan, libFuzzer's coverage instrumentation,
# -O1 with line tables) and builds the targets named on the command line there. One build directory
# for everything that runs under the sanitizers: the fuzz targets (scripts/fuzz.sh) and the
# daemon tier (scripts/sanitize_daemon.sh) share the libraries compiled once.
# Usage: scripts/sanitizer_build.sh TARGET...
set -euo pipefail
cd "$(dirname "$0")/.."
CXX_BIN=$(command -v clang++ || command -v clang++-14 || true)
if [ -z "$CXX_BIN" ]; then
  echo "sanitizer build: clang++ not found (scripts/deps.sh installs clang-14 and libclang-rt-14-dev)" >&2
  exit 1
fi
# ccache where installed (its base_dir makes the objects of other checkouts' builds reusable).
launcher=$(command -v ccache || true)
san="-fsanitize=fuzzer-no-link,address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer"
# -O1 and line tables only, as the sanitizers' own documentation advises: a report still names
# file and line of every frame, and on CI's 2-core machines this build is the longest step of
# the tests (27 Nov 2026: the run took 45 min). Against -O2 -g: solver/fit_trust.cpp 69 -> 54 s.
# No precompiled headers (-DMOCAP_PCH=OFF): this build keeps the includes of every file it
# compiles checked (with the numeric core linked from build/, not that core's).
# The numeric core (solver, report, tracker, simulation, reconstruction) is compiled without the
# sanitizers here anyway (fuzz/CMakeLists.txt): when the main build is there (ctest runs after
# it), link its archives instead of compiling them again (cmake/prebuilt_core.cmake), with the
# main build's -march, provided clang and gcc see the same vector ISA with it (Eigen's fixed-size
# types are aligned by it). Otherwise, or with MOCAP_SANITIZER_PREBUILT=0, compile everything.
core=(-DMOCAP_PREBUILT_DIR= -DMOCAP_NATIVE=OFF)
if [ "${MOCAP_SANITIZER_PREBUILT:-1}" = 1 ] && [ -f build/CMakeCache.txt ]; then
  native=$(sed -n 's/^MOCAP_NATIVE:BOOL=//p' build/CMakeCache.txt)
  gxx=$(sed -n 's/^CMAKE_CXX_COMPILER:[A-Z]*=//p' build/CMakeCache.txt)
  march=(); [ "$native" = ON ] && march=(-march=native)
  isa() { "$1" "${march[@]}" -dM -E -x c++ /dev/null | grep -oE '__(AVX|AVX512F)__' | sort | tr '\n' ' '; }
  # (A library whose archive build/ lacks is compiled here: cmake/prebuilt_core.cmake.)
  if [ -n "$gxx" ] && [ "$(isa "$gxx")" = "$(isa "$CXX_BIN")" ]; then
    core=(-DMOCAP_PREBUILT_DIR="$PWD/build" -DMOCAP_NATIVE="$native")
  else
    echo "sanitizer build: compiling the numeric core here too (the main build's vector ISA" \
         "differs from clang's)" >&2
  fi
fi
cmake -S . -B build-fuzz -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_CXX_COMPILER="$CXX_BIN" \
      -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -gline-tables-only -DNDEBUG" -DMOCAP_PCH=OFF \
      -DMOCAP_FUZZ=ON "${core[@]}" -DCMAKE_CXX_FLAGS="$san" \
      -DCMAKE_CXX_COMPILER_LAUNCHER="$launcher" >/dev/null
cmake --build build-fuzz -j"$(nproc)" --target "$@"
