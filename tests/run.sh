#!/usr/bin/env bash
# Install everything the tests need (system and Python packages), then run them all.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install.sh --dev
exec "${PYTHON:-python3}" -m pytest "$@"
