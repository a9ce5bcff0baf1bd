#!/usr/bin/env bash
# The project's test command: sets up its own virtual environment, then lint + format check + pytest.
# Usage: bash scripts/test.sh [extra pytest args]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/test_services.sh  # Debian nginx for tests/test_nginx.py, when it can be installed
VENV=${PHIM_VENV:-.venv}

"$VENV/bin/ruff" check .
"$VENV/bin/ruff" format --check .
# Two test processes (pytest-xdist), each file's tests in one of them: most tests use one core (one torch
# thread, a server and its client taking turns), so two processes keep both cores of a 2-core machine busy
# (docs/benchmarks.md). PHIM_TEST_WORKERS=0 runs everything in this process.
exec "$VENV/bin/python" -m pytest -q -n "${PHIM_TEST_WORKERS:-2}" --dist loadfile "$@"  # warnings are errors: pyproject.toml
