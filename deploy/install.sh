#!/usr/bin/env bash
# Install meniscope on this machine: the Debian packages it calls, then the Python package.
#   bash deploy/install.sh          runtime only (the service)
#   bash deploy/install.sh --dev    + training (torch, CPU build) and the test tools
set -euo pipefail
cd "$(dirname "$0")/.."

dev=0
[ "${1:-}" = "--dev" ] && dev=1

# System packages: harminv (peer fit), promtool (metrics check); for --dev also Blender
# (reference renderer) and ffmpeg. Installed only when missing, so reruns are quick.
need=(harminv:harminv promtool:prometheus)
[ "$dev" = 1 ] && need+=(blender:blender ffmpeg:ffmpeg)
missing=()
for pair in "${need[@]}"; do
  command -v "${pair%%:*}" >/dev/null 2>&1 || missing+=("${pair#*:}")
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
  "$py" -m pip install -q -e ".[train,test]"
else
  "$py" -m pip install -q -e .
fi
