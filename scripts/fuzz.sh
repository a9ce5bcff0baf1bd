#!/usr/bin/env bash
# The fuzz properties of tests/test_fuzz.py run long: PHIM_FUZZ_CASES cases per property (default 35,000:
# over 100,000 in all, against the decoder, the HTTP route and the zenoh queryable of a real server on
# loopback), and schemathesis (tests/test_schema_fuzz.py) with PHIM_SCHEMA_FUZZ_CASES per operation and
# phase (default 5,000). Prints pytest's summary and the wall time; record the result in docs/benchmarks.md.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash scripts/setup.sh
export PHIM_FUZZ_CASES="${PHIM_FUZZ_CASES:-35000}"
export PHIM_SCHEMA_FUZZ_CASES="${PHIM_SCHEMA_FUZZ_CASES:-5000}"
start=$(date +%s)
.venv/bin/python -m pytest tests/test_fuzz.py tests/test_schema_fuzz.py -q -p no:cacheprovider "$@"
echo "fuzz: 3 properties x $PHIM_FUZZ_CASES cases, schemathesis $PHIM_SCHEMA_FUZZ_CASES per operation and phase, in $(($(date +%s) - start)) s"
