#!/usr/bin/env bash
# The issue's 2-hour soak (issue 17, "Load"; BENCHMARKS.md "Soak") with mocapd at the priority the
# unit gives it (systemd/mocapd.service.in: Nice=-10, CPUWeight=1000). Outside systemd, on a
# machine with kernel.sched_autogroup_enabled, nice ranks threads within one session only: so the
# soak runs in a session of its own (setsid) whose autogroup is at nice -10 against the other
# sessions (the unit's CPUWeight), and at nice -10 inside it (the unit's Nice; mocapd, a child,
# inherits both, and its fit sets itself to nice 10). Needs root (CAP_SYS_NICE) for the -10s;
# without, it runs at the default priority and says so.
# Usage: scripts/soak.sh OUT_PREFIX [soak flags...]   (default flags: the issue's two hours)
# Writes OUT_PREFIX.log (the table) and OUT_PREFIX.json (every row); returns at once.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/soak.sh OUT_PREFIX [soak flags...]}
shift
flags=("$@")
[ ${#flags[@]} -gt 0 ] || flags=(--duration 120 --sample 60 --record-every 5 --fit-every 20)
setsid bash -c '
  if echo -10 > /proc/self/autogroup 2>/dev/null && renice -n -10 -p $$ >/dev/null 2>&1; then
    echo "soak: session $(cat /proc/self/autogroup), nice $(ps -o ni= -p $$), $(date -u +%FT%TZ)" >&2
  else
    echo "soak: not allowed to raise the priority (root needed): mocapd runs at the default" >&2
  fi
  exec ./build/bench/soak "$@"' soak "${flags[@]}" --json "$out.json" > "$out.log" 2>&1 < /dev/null &
echo "soak started: $out.log, $out.json"
