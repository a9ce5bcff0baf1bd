#!/usr/bin/env bash
# The fuzz properties of tests/test_fuzz.py run long: PHIM_FUZZ_CASES cases per property (default 35,000:
# over 100,000 in all, against the decoder, the HTTP route and the zenoh queryable of a real server on
# loopback). Prints pytest's summary and the wall time; record the result in docs/benchmarks.md.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash scripts/setup.sh
export PHIM_FUZZ_CASES="${PHIM_FUZZ_CASES:-35000}"
start=$(date +%s)
.venv/bin/python -m pytest tests/test_fuzz.py -q -p no:cacheprovider "$@"
echo "fuzz: 3 properties x $PHIM_FUZZ_CASES cases in $(($(date +%s) - start)) s"
