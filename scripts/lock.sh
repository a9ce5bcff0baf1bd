#!/usr/bin/env bash
# Regenerates constraints.txt: the exact version of every dependency of every extra, for Python 3.11 on Linux,
# except torch (scripts/setup.sh pins the CPU wheel for venvs and CI; GPU images bring their own CUDA build).
# scripts/setup.sh, CI and the Dockerfile install with `-c constraints.txt`. Needs uv (pip install uv).
set -euo pipefail
cd "$(dirname "$0")/.."
no_torch=$(mktemp)
trap 'rm -f "$no_torch"' EXIT
echo "torch; sys_platform == 'never'" >"$no_torch"  # drops torch and what only torch needs
uv pip compile pyproject.toml --all-extras --override "$no_torch" --python-version 3.11 \
    --python-platform x86_64-manylinux_2_28 --no-header --quiet -o constraints.txt
