#!/usr/bin/env bash
# The daemon tier under AddressSanitizer (with LeakSanitizer) and UBSan: the real mocapd on the
# simulated rig, built in build-fuzz/ with the fuzzers' flags (scripts/sanitizer_build.sh), driven
# by the daemon tier's tests of the main build (build/tests, MOCAP_TEST_MOCAPD). A report from
# the mocapd they start goes to build-fuzz/sanitizer-logs/ (ASAN_OPTIONS/UBSAN_OPTIONS log_path,
# since a daemon's stderr is its log file) and fails the run, whatever the test concluded.
#
# The subset: what fits CI's budget (scripts/test.sh under 25 minutes on 2 cores; BENCHMARKS.md
# "The daemon tier under ASan and UBSan": building the ASan mocapd is most of the cost, the run
# ~15 s) and does not depend on the real-time margin that the sanitizers' slowdown takes away:
# every state-changing method refused outside the control group, export paths, 4,000 random
# requests into the daemon, every documented request and error code, a bad config. Left out:
# test_daemon_faults (the disk-full and misbehaving-clients tests failed under ASan on the
# 8-camera rig at 200 Hz by timing alone: tracking lost, the loop queue full, RSS grown by ASan's
# quarantine, with no sanitizer report) and the whole session and systemd tests (minutes each).
#
# Usage: scripts/sanitize_daemon.sh [build|run|all|faults [FILTER]]   (default all)
#   build:  the fuzz targets and mocapd in build-fuzz/ (ctest's fixture, so that the
#           fuzz test and this one never run ninja in build-fuzz/ at once)
#   run:    the tests below, then the logs
#   faults: by hand, not in CI (its ~80 s run and the test's build do not fit CI's budget):
#           builds and runs test_daemon_faults (FILTER, default all but the 20 SIGKILLs, which
#           take minutes under ASan). Its rigs run at an eighth of the rate in this build
#           (tests/test_daemon_faults.cpp kRateDivisor), and ASan keeps 16 MB of freed memory
#           in quarantine instead of 256 MB, so that the RSS bound of the misbehaving-clients
#           test measures mocapd, not ASan.
set -euo pipefail
cd "$(dirname "$0")/.."
what=${1:-all}
# test executable : gtest filter
tier=(
  "test_daemon_security:*"
  "test_daemon:*ProtocolEveryRequestAndEveryError*:*RefusesABadConfig*"
)
quarantine=""
# The tier's tests are this build's (build/tests, gcc) driving build-fuzz/'s mocapd
# (MOCAP_TEST_MOCAPD, tests/daemon_test_util.h): what runs under the sanitizers is the daemon.
tests_dir=build/tests
if [ "$what" = faults ]; then
  # test_daemon_faults is built here with MOCAP_TEST_UNDER_ASAN (its rigs at an eighth of the rate).
  tier=("test_daemon_faults:${2:--*KilledAtRandomMoments*}")
  quarantine=":quarantine_size_mb=16"
  tests_dir=build-fuzz/tests
  bash scripts/sanitizer_build.sh mocapd test_daemon_faults
fi
if [ "$what" = build ] || [ "$what" = all ]; then
  targets=(mocapd)
  for src in fuzz/fuzz_*.cpp; do targets+=("$(basename "$src" .cpp)"); done
  bash scripts/sanitizer_build.sh "${targets[@]}"
fi
[ "$what" = build ] && exit 0
for t in "${tier[@]}"; do
  if [ ! -x "$tests_dir/${t%%:*}" ]; then
    echo "sanitized daemon tier: $tests_dir/${t%%:*} is not built (scripts/build.sh builds build/)" >&2
    exit 1
  fi
done
export MOCAP_TEST_MOCAPD=$PWD/build-fuzz/daemon/mocapd

logs=$PWD/build-fuzz/sanitizer-logs
rm -rf "$logs"
mkdir -p "$logs"
export ASAN_OPTIONS="log_path=$logs/asan:detect_leaks=1:strict_string_checks=1:detect_stack_use_after_return=1$quarantine"
export UBSAN_OPTIONS="log_path=$logs/ubsan:print_stacktrace=1:halt_on_error=1"
failed=()
for t in "${tier[@]}"; do
  exe=${t%%:*} filter=${t#*:}
  start=$(date +%s)
  if ! "$tests_dir/$exe" --gtest_filter="$filter" >"$logs/../$exe.log" 2>&1; then
    tail -n 40 "$logs/../$exe.log" >&2
    failed+=("$exe")
  fi
  echo "sanitized daemon tier: $exe ($filter): $(( $(date +%s) - start )) s, $(grep -c '^\[       OK' "$logs/../$exe.log" || true) passed"
done
reports=$(find "$logs" -type f | sort)
if [ -n "$reports" ]; then
  for r in $reports; do echo "=== $r" >&2; head -n 60 "$r" >&2; done
  echo "sanitized daemon tier: sanitizer reports in $logs" >&2
  exit 1
fi
if [ ${#failed[@]} -gt 0 ]; then
  echo "sanitized daemon tier: FAILED: ${failed[*]} (logs in build-fuzz/)" >&2
  exit 1
fi
echo "sanitized daemon tier: clean (ASan, LSan, UBSan)"
