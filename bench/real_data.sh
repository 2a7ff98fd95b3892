#!/usr/bin/env bash
# The real-data figures of BENCHMARKS.md ("Real data (issue 3)"): `mocap fit` and `mocap ik` on the
# recordings of ../shared/data, each command timed, the report's figures printed. The comparison
# with OpenSim's own result (same frames, markers and kinematics) is printed by
# `build/tests/test_real_data`. Usage: bench/real_data.sh [OUT_DIR (default build/bench_real_data)]
set -euo pipefail
cd "$(dirname "$0")/.."
mocap=build/tools/mocap
data=../shared/data
out=${1:-build/bench_real_data}
mkdir -p "$out"
g=$data/opensim_gait2354_subject01 w=$data/welk007_hipfunc b=$data/biobuddy_p01_lowerlimb

run() {  # name, then the mocap arguments
  local name=$1
  shift
  local start end
  start=$(date +%s.%N)
  "$mocap" "$@" >"$out/$name.log" 2>&1
  end=$(date +%s.%N)
  printf '%-22s wall %6.1f s  ' "$name" "$(echo "$end - $start" | bc)"
  grep -E "^fit:" "$out/$name.log" | sed 's/^fit: //' || grep -E "marker RMS" "$out/$name.log" | tail -n +1
}
report() {  # report.json, parameter names...
  python3 - "$@" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
print("  per trial:", ", ".join(f"{t['name']} {t['marker_rms_mm']:.2f} mm" for t in r["per_trial"]))
for p in r["parameters"]:
    if p["name"] in sys.argv[2:]:
        print(f"  {p['name']} = {p['value']:.4f} m +- {1000 * p['std']:.2f} mm (initial {p['initial']:.4f})")
PY
}

run gait2354_fit fit --model $g/gait2354_simbody.osim --marker-set $g/gait2354_Scale_MarkerSet.xml \
    $g/subject01_static.trc $g/subject01_walk1.trc --out "$out/gait2354/fitted.osim" \
    --report "$out/gait2354/report.json" --threads 2 --max-iterations 300
report "$out/gait2354/report.json"
run gait2354_ik ik --model $g/reference_outputs/subject01_simbody.osim $g/subject01_walk1.trc \
    --out "$out/gait2354_ik/walk1.mot"

run welk007_scale fit --model $w/unscaled_generic.osim $w/c3d_Trimmed_static1.c3d $w/c3d_Trimmed_RHJC1.c3d \
    --fit scales,markers --out "$out/welk007/scaled.osim" --report "$out/welk007/scaled.json" \
    --threads 2 --max-iterations 100
run welk007_centres fit --model "$out/welk007/scaled.osim" $w/c3d_Trimmed_static1.c3d $w/c3d_Trimmed_RHJC1.c3d \
    --fit centres,markers --out "$out/welk007/fitted.osim" --report "$out/welk007/report.json" \
    --threads 2 --max-iterations 100
report "$out/welk007/report.json" hip_r.centre.x hip_r.centre.y hip_r.centre.z r.ASIS.x r.ASIS.y r.ASIS.z
run welk007_all_at_once fit --model $w/unscaled_generic.osim $w/c3d_Trimmed_static1.c3d $w/c3d_Trimmed_RHJC1.c3d \
    --fit centres,markers --out "$out/welk007_once/fitted.osim" --report "$out/welk007_once/report.json" \
    --threads 2 --max-iterations 100
report "$out/welk007_once/report.json" hip_r.centre.x hip_r.centre.y hip_r.centre.z

"$mocap" model default --out "$out/default.json"
run biobuddy_fit fit --model "$out/default.json" $b/*.c3d --fit scales,centres,markers \
    --out "$out/biobuddy/fitted.json" --report "$out/biobuddy/report.json" --threads 2 --max-iterations 300
report "$out/biobuddy/report.json"
