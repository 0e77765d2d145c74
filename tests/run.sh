#!/usr/bin/env bash
# Install everything the tests need (system packages, and the Python ones into the virtual
# environment deploy/install.sh makes), then run them all with that environment's Python.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install.sh --dev
exec "${MENISCOPE_VENV:-$PWD/.venv}/bin/python" -m pytest "$@"
