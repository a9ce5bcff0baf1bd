#!/usr/bin/env bash
# Ten minutes of scripts/soak.py (a real server at twice its ceiling over HTTP and zenoh; every sector
# answered once, RSS flat, streams evicted after): pass its options through, e.g. --duration 60.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash scripts/setup.sh
exec .venv/bin/python scripts/soak.py "$@"
