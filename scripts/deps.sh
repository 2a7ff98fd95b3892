#!/usr/bin/env bash
# Installs the Debian 12 packages mocapd needs, only those that are missing.
set -euo pipefail
PKGS=(cmake ninja-build g++ pkg-config
      libeigen3-dev libsuitesparse-dev libopenblas-dev
      libceres-dev libcli11-dev nlohmann-json3-dev libspdlog-dev
      libgtest-dev libgmock-dev libbenchmark-dev libtinyxml2-dev libtomlplusplus-dev
      libaravis-dev aravis-tools libusb-1.0-0-dev libopencv-dev
      libsqlite3-dev libsystemd-dev  # mocapd: the store (SQLite), sd-event, sd-daemon
      systemd dpkg-dev  # tests/test_daemon_systemd: systemd-socket-activate, systemd-analyze, dpkg-shlibdeps (cpack -G DEB)
      jq bc  # scripts/demo.sh reads mocapctl --json
      chromium  # tests/test_report: the fit report page opened headless; scripts/report_screenshot.sh
      clang-14 libclang-rt-14-dev)  # clang + libFuzzer: scripts/fuzz.sh
missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "deps: installing ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
# Dense kernels of CHOLMOD and Ceres go through BLAS: pick OpenBLAS deliberately, not the reference BLAS.
if command -v update-alternatives >/dev/null; then
  arch=$(dpkg --print-architecture 2>/dev/null | sed 's/amd64/x86_64/;s/arm64/aarch64/')
  for lib in libblas.so.3 liblapack.so.3; do
    cand=$(update-alternatives --list "${lib}-${arch}-linux-gnu" 2>/dev/null | grep openblas | head -1 || true)
    [ -n "$cand" ] && ${SUDO:-} update-alternatives --set "${lib}-${arch}-linux-gnu" "$cand" >/dev/null 2>&1 || true
  done
fi
