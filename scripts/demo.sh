#!/usr/bin/env bash
# The main job end to end on its built-in default: mocapd on the simulated rig
# (daemon/examples/simulated-rig.toml: 8 Aravis fake cameras, 1280x1024, 200 Hz, the virtual
# subject of `mocap sim --seed 1`), driven through its control socket by mocapctl, as an operator
# runs a subject calibration session:
#   1. calibrate the rig: the virtual operator waves the wand through the volume, then lays the
#      L-frame; bundle adjustment; the calibration is applied to triangulation;
#   2. create the subject (its height measured: the virtual subject's) and select it: the EKF
#      tracker starts on the nominal model and initialises itself from the static pose;
#   3. record every movement of the protocol; the subject performs what the operator asks, and
#      after each recording the daemon checks that it covered what the movement must excite.
#      Squats are first performed at 40 % of the range: the check fails, names the joint, and the
#      movement is repeated;
#   4. fit the subject's model to every recording (one global sparse LM), apply it to the live
#      tracker between two frames, export a recording (C3D) and the model;
#   5. compare the fitted model with the virtual subject's truth, and stop the daemon.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/build.sh
out=${1:-/tmp/mocap-demo}
rm -rf "$out"
mkdir -p "$out"
mocapd=./build/daemon/mocapd
ctl=(./build/daemon/mocapctl --socket "$out/control.sock")
mocap=./build/tools/mocap
# Movements at half their protocol length: the same ranges, fewer cycles.
scale=${MOCAP_DEMO_DURATION_SCALE:-0.5}

"$mocapd" --config daemon/examples/simulated-rig.toml --state-dir "$out/state" \
    --socket "$out/control.sock" --export-dir "$out" 2>"$out/mocapd.log" &
pid=$!
trap 'kill "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true' EXIT
for _ in $(seq 150); do "${ctl[@]}" status >/dev/null 2>&1 && break; sleep 0.2; done
step() { printf '\n== %s (%s)\n' "$1" "$(date +%T)"; }
t0=$(date +%s.%N)
lap() { printf '   [%s: %.1f s]\n' "$1" "$(echo "$(date +%s.%N) - $t0" | bc)"; t0=$(date +%s.%N); }

step "rig calibration"
"${ctl[@]}" calibrate --seconds 15 --apply
lap "rig calibration"

step "subject"
height=$("${ctl[@]}" --json status | jq -r .rig.virtual_subject.height_m)
"${ctl[@]}" subject create S01 --height "$height"
"${ctl[@]}" subject select S01
for _ in $(seq 100); do
  [ "$("${ctl[@]}" --json status | jq -r .tracker.state)" = tracking ] && break
  sleep 0.2
done
"${ctl[@]}" status
lap "subject"

step "recordings"
if "${ctl[@]}" record squats --sim-amplitude 0.4 --sim-duration-scale "$scale"; then
  echo "the under-performed squats passed the coverage check: that is a bug" >&2
  exit 1
fi
echo "   (as the operator was told: repeat it, properly)"
for m in $("${ctl[@]}" --json protocol | jq -r '.movements[].name'); do
  # As an operator does: a movement whose coverage check fails (exit 4) is repeated.
  for attempt in 1 2 3; do
    status=0
    "${ctl[@]}" record "$m" --sim-duration-scale "$scale" || status=$?
    [ "$status" -eq 0 ] && break
    [ "$status" -eq 4 ] || exit "$status"
    echo "   (repeating $m, as the daemon advised)"
  done
  lap "record $m"
done

step "fit"
"${ctl[@]}" fit
lap "fit"
"${ctl[@]}" apply
lap "apply"

step "export"
"${ctl[@]}" recordings
first=$("${ctl[@]}" --json recordings | jq -r '[.recordings[] | select(.coverage_ok)][0].id')
"${ctl[@]}" export recording "$first" --format c3d --out "$out/static.c3d"
"${ctl[@]}" export recording "$first" --format trc --out "$out/static.trc"
version=$("${ctl[@]}" --json models | jq -r '.models[-1].version')
"${ctl[@]}" export model "$version" --format json --out "$out/fitted.model.json"

step "the fitted model against the virtual subject's truth"
"$mocap" sim --out "$out/sim" --seed 1 --rate 200 --noise-mm 0 >/dev/null
echo "nominal (before the fit):"
"$mocap" model diff "$out/sim/truth.model.json" "$out/sim/nominal.model.json" | tail -5
echo "fitted:"
"$mocap" model diff "$out/sim/truth.model.json" "$out/fitted.model.json"

"${ctl[@]}" shutdown
wait "$pid"
trap - EXIT
echo "daemon log: $out/mocapd.log"
