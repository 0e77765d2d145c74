#!/usr/bin/env bash
# Install meniscope on this machine: the Debian packages it calls, then the Python package.
#   bash deploy/install.sh          runtime only (the service)
#   bash deploy/install.sh --dev    + training (torch, CPU build, Dask for scale-out) and the test tools
set -euo pipefail
cd "$(dirname "$0")/.."

dev=0
[ "${1:-}" = "--dev" ] && dev=1

# Debian packages: harminv (peer fit), prometheus (promtool, metrics check); Aravis and its
# GObject bindings (GigE Vision / USB3 cameras, with a fake camera for tests) plus what
# PyGObject builds against; for --dev also Blender (reference renderer), ffmpeg, docker-compose
# (validates docker-compose.yml offline; no Docker engine is needed or started), and Chromium with its
# WebDriver (the dashboard's browser test).
# Installed only when missing, so reruns are quick.
need=(harminv prometheus aravis-tools gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config gcc)
[ "$dev" = 1 ] && need+=(blender ffmpeg docker-compose chromium chromium-driver)
missing=()
for pkg in "${need[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
  sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

py=${PYTHON:-python3}
if [ "$dev" = 1 ]; then
  # the CPU build; an unpinned torch would pull GBs of CUDA packages
  "$py" -m pip install -q "torch==2.13.0"
  "$py" -m pip install -q -e ".[aravis,train,scale,test]"
else
  "$py" -m pip install -q -e ".[aravis]"
fi
# compile the window fit's numba kernels now (cached beside the code), not at the service's first window
"$py" -c "from service.analysis.fit import warm; warm()"
