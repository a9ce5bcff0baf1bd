#!/usr/bin/env bash
# On a GPU machine whose python3 already holds a CUDA build of torch (plus numpy, typer, rich, pytest):
# the CUDA parity tests, then the model benchmarks for the GPU rows of docs/benchmarks.md.
# Needs the KITTI scans 000000/000001 at ../shared/data/kitti_object/velodyne, as the CPU tests do.
# Usage: bash scripts/gpu_session.sh [OUTDIR]   (JSON results and logs land in OUTDIR, default runs/gpu)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-runs/gpu}
mkdir -p "$out"
py=${PYTHON:-python3}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
"$py" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" | tee -a "$out/gpu.txt"
"$py" -m pytest -q -W error -p no:cacheprovider tests/test_cuda.py 2>&1 | tee "$out/test_cuda.log" ||
    echo "CUDA TESTS FAILED (benchmarks follow anyway)"
phim() { "$py" -m model.cli "$@"; }
phim model info --config paper --json >"$out/info_paper.json"
rows=()
for run in "paper 1 auto" "paper 8 auto" "paper 1 chunked" "tiny 1 auto" "tiny 8 auto"; do
    set -- $run
    phim bench model --config "$1" --batch "$2" --scan "$3" --device cuda --turns 20 --json \
        >"$out/bench_$1_b$2_$3.json"
    rows+=("$("$py" -c "import json,sys; r=json.load(open(sys.argv[1])); print('| %s | %s | %d | %s | %s | %s | %s | %s |' % (r['config'], r['scan'], r['batch'], r['p50_ms'], r['p90_ms'], r['per_sector_p50_ms'], r['peak_mem_mb'], r['full_turn_peak_mem_mb']))" "$out/bench_$1_b$2_$3.json")")
done
echo
cat "$out/gpu.txt"
"$py" -c "import json,sys; r=json.load(open(sys.argv[1])); print('paper: params', r['params'], 'gflops', r['gflops'])" "$out/info_paper.json"
echo "| config | scan | streams | p50 ms | p90 ms | per-sector p50 ms | peak MB | full-turn peak MB |"
echo "|---|---|---|---|---|---|---|---|"
printf '%s\n' "${rows[@]}"
