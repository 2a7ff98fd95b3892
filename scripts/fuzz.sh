#!/usr/bin/env bash
# Builds the libFuzzer targets of fuzz/ with clang, AddressSanitizer and UBSan in build-fuzz/
# (scripts/sanitizer_build.sh), and
# runs each for a bounded time, seeded with fuzz/seeds/NAME/ (small files covering the formats'
# variants), the files *.NAME of ../shared/data, and the corpus it grew before (fuzz_NAME reads
# *.NAME), with the dictionary fuzz/NAME.dict where there is one. Exits non-zero on a crash (the input is kept in
# build-fuzz/artifacts/) or when the build fails.
# Usage: scripts/fuzz.sh [seconds per target, default 60]
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${1:-60}
targets=()
for src in fuzz/fuzz_*.cpp; do targets+=("$(basename "$src" .cpp)"); done
bash scripts/sanitizer_build.sh "${targets[@]}"

shared=../shared/data
failed=()
for t in "${targets[@]}"; do
  ext=${t#fuzz_}
  corpus=build-fuzz/corpus/$t seeds=build-fuzz/seeds/$t
  mkdir -p "$corpus" "$seeds" build-fuzz/artifacts
  [ -d "fuzz/seeds/$ext" ] && cp -f fuzz/seeds/"$ext"/* "$seeds/"
  if [ -d "$shared" ]; then
    find "$shared" -name "*.$ext" -exec cp -f {} "$seeds/" \;
  else
    echo "fuzz: $shared is absent: $t starts from its own corpus only"
  fi
  dict=()
  [ -f "fuzz/$ext.dict" ] && dict=(-dict="fuzz/$ext.dict")
  # The framing fuzzer gets a third of the time and the daemon's dispatch two thirds: the
  # daemon's inputs pass through the same server and framing, and together they take one
  # target's time (CI's budget: tests/CMakeLists.txt).
  case $t in
    fuzz_control) tsecs=$(( secs / 3 )) ;;
    fuzz_daemon) tsecs=$(( secs - secs / 3 )) ;;
    *) tsecs=$secs ;;
  esac
  echo "fuzz: $t for ${tsecs} s ($(ls "$seeds" | wc -l) seed files)"
  # Seeds past max_len are cut to it (the header and parameters are at the front): small inputs
  # keep the runs fast; the mutations of the frame counts make the cut files whole again.
  if ! "build-fuzz/fuzz/$t" -max_total_time="$tsecs" -timeout=10 -rss_limit_mb=2048 \
       -max_len=65536 -print_final_stats=1 "${dict[@]}" -artifact_prefix="build-fuzz/artifacts/$t-" \
       "$corpus" "$seeds" 2>"build-fuzz/$t.log"; then
    tail -n 60 "build-fuzz/$t.log" >&2
    failed+=("$t")
  else
    grep -E "^(Done|stat::number_of_executed_units|stat::peak_rss_mb)" "build-fuzz/$t.log" || true
  fi
done
if [ ${#failed[@]} -gt 0 ]; then
  echo "fuzz: FAILED: ${failed[*]} (crashing inputs in build-fuzz/artifacts/)" >&2
  exit 1
fi
echo "fuzz: ${#targets[@]} targets ran without a crash (${secs} s each; fuzz_control and fuzz_daemon share ${secs} s)"
