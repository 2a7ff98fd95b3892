#!/usr/bin/env bash
# Regenerates docs/fit-report.png, the README's picture of the fit report page: the subject of
# `mocap sim --seed 1` (the one scripts/demo.sh records and fits), fitted to every trial with
# `mocap fit --html`, opened by headless Chromium (Debian's `chromium`, scripts/deps.sh).
# Usage: scripts/report_screenshot.sh [BUILD_DIR]   (default: build)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
mocap="$build/tools/mocap"
[ -x "$mocap" ] || { echo "report_screenshot: $mocap not built (cmake --build $build --target mocap)" >&2; exit 1; }
command -v chromium >/dev/null || { echo "report_screenshot: chromium is not installed (scripts/deps.sh)" >&2; exit 1; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$mocap" sim --out "$work/sim" --seed 1 --duration-scale 0.5 >/dev/null
trials=$(ls "$work"/sim/*.trc | grep -v joint_centres)
# shellcheck disable=SC2086
"$mocap" fit --model "$work/sim/nominal.model.json" $trials --threads 2 --protocol default \
  --out "$work/fit/fitted.json" --report "$work/fit/report.json" --html "$work/fit/report.html" >/dev/null
mkdir -p "$root/docs"
chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
  --disable-background-networking --disable-component-update --disable-sync \
  --user-data-dir="$work/profile" --hide-scrollbars --window-size=1280,1500 \
  --screenshot="$work/shot.png" "file://$work/fit/report.html" 2>/dev/null
# A palette PNG (the page has few colours) keeps the picture small in the repository.
python3 - "$work/shot.png" "$root/docs/fit-report.png" <<'PY'
import sys
try:
    from PIL import Image
    Image.open(sys.argv[1]).convert("RGB").quantize(colors=64).save(sys.argv[2], optimize=True)
except ImportError:
    import shutil
    shutil.copy(sys.argv[1], sys.argv[2])
PY
echo "wrote $root/docs/fit-report.png ($(stat -c %s "$root/docs/fit-report.png") bytes)"
