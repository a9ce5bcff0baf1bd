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
exec "$VENV/bin/python" -m pytest -q "$@"  # warnings are errors: pyproject.toml, filterwarnings
