#!/usr/bin/env bash
# Starts the detection server on the embedded default model (sets up .venv first if needed).
# Usage: bash scripts/serve.sh [phim serve flags]   e.g. --port 8081 --no-zenoh
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec "${PHIM_VENV:-.venv}/bin/phim" serve "$@"
