#!/usr/bin/env bash
# The main job end to end on its built-in default, simulated cameras and the default subject:
#   1. the subject of `mocap sim --seed 1` performs the calibration protocol (60 s) in front of 8
#      simulated cameras (Aravis fake devices, 1280x1024, 200 Hz); detection, sync and
#      triangulation run in real time -> unlabelled 3D points;
#   2. the EKF tracker, with the NOMINAL model (as before any calibration), finds the subject in
#      its static pose, labels the points and tracks the skeleton -> labelled markers + poses;
#   3. the global fit identifies the subject's model from every frame, starting from the
#      tracker's poses;
#   4. both models are compared with the truth.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/build.sh
out=${1:-/tmp/mocap-demo}
rm -rf "$out"; mkdir -p "$out"
mocap=./build/tools/mocap
$mocap sim --out "$out/sim" --seed 1 --rate 200 --noise-mm 0  # the true and nominal models
$mocap capture --simulate --seed 1 --seconds 61 --out "$out/capture"
$mocap track --points "$out/capture/points.c3d" --model "$out/sim/nominal.model.json" \
    --out "$out/track"
$mocap fit --model "$out/sim/nominal.model.json" "$out/track/labelled.trc" \
    --initial "$out/track/coordinates.mot" --out "$out/fitted.model.json" \
    --report "$out/report.json"
echo "== capture (against the truth) =="
cat "$out/capture/stats.json"
echo "== nominal model against the truth =="
$mocap model diff "$out/sim/truth.model.json" "$out/sim/nominal.model.json" | tail -5
echo "== fitted model against the truth =="
$mocap model diff "$out/sim/truth.model.json" "$out/fitted.model.json"
