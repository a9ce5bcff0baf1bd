#!/usr/bin/env bash
# Creates the project's virtual environment (.venv, or $PHIM_VENV) if needed and installs the project into it
# with the pinned CPU build of PyTorch. Used by scripts/test.sh and scripts/serve.sh; safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${PHIM_VENV:-.venv}
PY=${PYTHON:-python3}
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
# CPU torch wheel pinned for local venvs and CI; GPU images install their CUDA build (see Dockerfile).
"$VENV/bin/python" -m pip install -q --disable-pip-version-check torch==2.13.0
"$VENV/bin/python" -m pip install -q --disable-pip-version-check -e ".[server,clients,dev]"
