#!/usr/bin/env bash
# Install meniscope on this machine: the Debian packages it calls, then the Python package into a
# virtual environment of its own (Debian's /usr/bin/python3 is "externally managed", PEP 668: pip
# may not install into it), and a `meniscope` command on the PATH.
#   bash deploy/install.sh          runtime only (the service)
#   bash deploy/install.sh --dev    + training (torch, CPU build, Dask for scale-out) and the test tools
# Environment (all optional):
#   PYTHON          the Python (>= 3.11) the environment is made from; default python3
#   MENISCOPE_VENV  where the environment goes; default .venv in this checkout
#   MENISCOPE_BIN   where the `meniscope` link goes; default /usr/local/bin as root, else ~/.local/bin
#   MENISCOPE_NO_WARM=1  leave the fit's kernels to compile at the first window (tests/test_install.py: the
#                   test command's own install has compiled them once already)
set -euo pipefail
cd "$(dirname "$0")/.."

dev=0
[ "${1:-}" = "--dev" ] && dev=1

py=${PYTHON:-python3}
if ! "$py" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  echo "install.sh: meniscope needs Python 3.11 or newer; '$py' is $("$py" --version 2>&1 || echo missing). Set PYTHON=/path/to/python3.11" >&2
  exit 1
fi

# Debian packages: python3-venv (Debian's Python makes virtual environments only with it); harminv
# (peer fit), prometheus (promtool, metrics check); Aravis and its GObject bindings (GigE Vision /
# USB3 cameras, with a fake camera for tests) plus what PyGObject builds against; for --dev also
# Blender (reference renderer), ffmpeg, xxhash (xxhsum: checks a report's digest), docker-compose
# (validates docker-compose.yml offline; no Docker engine is needed or started), and Chromium with its
# WebDriver (the dashboard's browser test).
# Installed only when missing, so reruns are quick.
need=(python3-venv harminv prometheus aravis-tools gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config gcc)
[ "$dev" = 1 ] && need+=(blender ffmpeg docker-compose chromium chromium-driver xxhash)
missing=()
for pkg in "${need[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
  sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

venv=${MENISCOPE_VENV:-$PWD/.venv}
[ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
vpy="$venv/bin/python"
if [ "$dev" = 1 ]; then
  # the CPU build; an unpinned torch would pull GBs of CUDA packages
  "$vpy" -m pip install -q "torch==2.13.0"
  "$vpy" -m pip install -q -e ".[aravis,train,scale,test]"
  # pycine (a .cine reader the tests use as an oracle) without its dependencies: it requires
  # opencv-python, a second OpenCV that would overwrite cv2 of opencv-contrib-python-headless
  "$vpy" -m pip install -q --no-deps "pycine==0.3.2"
else
  "$vpy" -m pip install -q -e ".[aravis]"
fi
# compile the window fit's numba kernels now (cached beside the code), not at the service's first window
[ "${MENISCOPE_NO_WARM:-0}" = 1 ] || "$vpy" -c "from service.analysis.fit import warm; warm()"

# the command, where a shell finds it
if [ -n "${MENISCOPE_BIN:-}" ]; then bin=$MENISCOPE_BIN
elif [ "$(id -u)" = 0 ]; then bin=/usr/local/bin
else bin=$HOME/.local/bin
fi
mkdir -p "$bin"
ln -sf "$venv/bin/meniscope" "$bin/meniscope"
echo "install.sh: meniscope installed in $venv; the command is $bin/meniscope"
case ":$PATH:" in
  *":$bin:"*)
    first=$(command -v meniscope || true)
    if [ "$first" != "$bin/meniscope" ]; then
      echo "install.sh: another meniscope comes first on your PATH ($first); run $bin/meniscope" >&2
    fi ;;
  *) echo "install.sh: $bin is not on your PATH: add it (export PATH=\"$bin:\$PATH\") or run $bin/meniscope" >&2 ;;
esac
