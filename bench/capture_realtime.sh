#!/usr/bin/env bash
# The capture target of issue 4: 8 simulated cameras (Aravis fake devices), 1280x1024, 200 Hz,
# the default subject's 39 markers, 0.1 px centroid noise, through detection, sync and
# triangulation in real time on this machine. Prints stats.json.
#   bash bench/capture_realtime.sh [SECONDS] [OUT_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-10}
out=${2:-$(mktemp -d)/capture}
[ -x build/tools/mocap ] || bash scripts/build.sh
./build/tools/mocap capture --simulate --cameras 8 --width 1280 --height 1024 --rate 200 \
    --seconds "$seconds" --out "$out"
echo "load average: $(cut -d' ' -f1-3 /proc/loadavg)"
cat "$out/stats.json"
