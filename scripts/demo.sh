#!/usr/bin/env bash
# The main job on its built-in default: simulate the default subject performing the
# calibration protocol, fit the body model to it, and show how close the fit came to the truth.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/build.sh
out=${1:-/tmp/mocap-demo}
rm -rf "$out"; mkdir -p "$out"
./build/tools/mocap sim --out "$out/sim" --seed 1
./build/tools/mocap fit --model "$out/sim/nominal.model.json" "$out"/sim/*.trc \
    --out "$out/fitted.model.json" --report "$out/report.json"
echo "== nominal model against the truth =="
./build/tools/mocap model diff "$out/sim/truth.model.json" "$out/sim/nominal.model.json"
echo "== fitted model against the truth =="
./build/tools/mocap model diff "$out/sim/truth.model.json" "$out/fitted.model.json"
