#!/usr/bin/env bash
# The daemon tier under ThreadSanitizer, by hand (not in CI: the TSan build of mocapd and its
# libraries is another full build, and test_daemon takes minutes at TSan's 5-15x slowdown).
# Builds mocapd, mocapctl and test_daemon in build-tsan/ (clang, -fsanitize=thread, RelWithDebInfo,
# ccache) and runs test_daemon (a filter may narrow it) against that mocapd. TSan's reports from
# any process (the test, each mocapd it starts, mocapctl) go to build-tsan/tsan-logs/ (a daemon's
# stderr is its log file); the run fails when there is one.
#
# Usage: scripts/tsan_daemon.sh [gtest filter, default *]
set -euo pipefail
cd "$(dirname "$0")/.."
filter=${1:-*}
CXX_BIN=$(command -v clang++ || command -v clang++-14 || true)
if [ -z "$CXX_BIN" ]; then
  echo "tsan: clang++ not found (scripts/deps.sh installs clang-14)" >&2
  exit 1
fi
launcher=$(command -v ccache || true)
cmake -S . -B build-tsan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_CXX_COMPILER="$CXX_BIN" \
      -DMOCAP_NATIVE=OFF -DCMAKE_CXX_FLAGS="-fsanitize=thread -fno-omit-frame-pointer" \
      -DCMAKE_CXX_COMPILER_LAUNCHER="$launcher" >/dev/null
nice cmake --build build-tsan -j"$(nproc)" --target mocapd mocapctl test_daemon

logs=$PWD/build-tsan/tsan-logs
rm -rf "$logs"
mkdir -p "$logs"
# halt_on_error=0: every race of the run is reported, not only the first. second_deadlock_stack:
# a lock-order report names both acquisitions.
# scripts/tsan.supp: the races TSan cannot judge (glib's and Aravis's hand-overs).
export TSAN_OPTIONS="log_path=$logs/tsan:halt_on_error=0:second_deadlock_stack=1:suppressions=$PWD/scripts/tsan.supp"
start=$(date +%s)
status=0
build-tsan/tests/test_daemon --gtest_filter="$filter" >build-tsan/test_daemon.log 2>&1 || status=$?
echo "tsan: test_daemon ($filter): $(( $(date +%s) - start )) s, exit $status," \
     "$(grep -c '^\[       OK' build-tsan/test_daemon.log || true) passed"
reports=$(find "$logs" -type f | sort)
if [ -n "$reports" ]; then
  # One line per distinct race: the first frame of each of its two accesses.
  for r in $reports; do
    grep -A3 -E "^WARNING: ThreadSanitizer" "$r" | grep -E "WARNING|#0" | sed 's/^ *//' || true
  done | sort | uniq -c | sort -rn | head -n 60
  echo "tsan: reports in $logs ($(echo "$reports" | wc -l) files)" >&2
  exit 1
fi
[ "$status" -eq 0 ] || { tail -n 40 build-tsan/test_daemon.log >&2; exit "$status"; }
echo "tsan: clean"
