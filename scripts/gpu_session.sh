#!/usr/bin/env bash
# On a GPU machine whose python3 already holds a CUDA build of torch (plus numpy, msgspec, click, rich, pytest):
# the CUDA parity tests, then the model benchmarks for the GPU rows of docs/benchmarks.md and the op counts.
# Needs the KITTI scans 000000/000001 at ../shared/data/kitti_object/velodyne, as the CPU tests do.
# Usage: bash scripts/gpu_session.sh [OUTDIR]   (JSON results and logs land in OUTDIR, default runs/gpu)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-runs/gpu}
mkdir -p "$out"
py=${PYTHON:-python3}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
"$py" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" | tee -a "$out/gpu.txt"
"$py" -m pytest -q -p no:cacheprovider tests/test_cuda.py 2>&1 | tee "$out/test_cuda.log" ||
    echo "CUDA TESTS FAILED (benchmarks follow anyway)"
phim() { "$py" -m phim "$@"; }
phim model info --config paper --json >"$out/info_paper.json"
for run in "paper 1 eager" "paper 1 graph" "paper 8 eager" "paper 8 graph" "paper 1 fixed" \
    "tiny 1 eager" "tiny 1 graph" "tiny 8 eager" "tiny 8 graph" \
    "paper 1 graph bf16" "paper 8 graph bf16" "tiny 8 graph bf16"; do
    set -- $run
    precision=${4:-fp32}
    phim bench model --config "$1" --batch "$2" --engine "$3" --precision "$precision" --device cuda --turns 20 \
        --json >"$out/bench_$1_b$2_$3_$precision.json"
done
for precision in fp32 bf16; do  # the shipped model's accuracy in each precision (docs/benchmarks.md)
    phim eval --checkpoint default --data sim --scans 100 --device cuda --precision "$precision" --json \
        >"$out/eval_tiny_$precision.json"
done
PYTHONPATH=. "$py" scripts/bf16_agreement.py --device cuda --engine graph | tee "$out/bf16_agreement.txt"
for config in paper tiny; do  # ops, CUDA kernels and host syncs of one step, by model function
    for engine in eager graph; do
        phim bench ops --config "$config" --engine "$engine" --device cuda --rows 30 >"$out/ops_${config}_$engine.md"
    done
done
echo
cat "$out/gpu.txt" "$out/ops_paper_eager.md" "$out/ops_paper_graph.md"
"$py" - "$out" <<'PY'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
info = json.loads((out / "info_paper.json").read_text())
print("paper: params", info["params"], "gflops", info["gflops"])
step_gflops = {"paper": 727.2, "tiny": 1.24}  # one streaming step (docs/benchmarks.md, phim model info)
print("| config | engine | precision | streams | p50 ms | p90 ms | per-sector p50 ms | TFLOP/s | peak MB |")
print("|---|---|---|---|---|---|---|---|---|")
for f in sorted(out.glob("bench_*.json")):
    r = json.loads(f.read_text())
    tflops = step_gflops[r["config"]] * r["batch"] / r["p50_ms"]  # GFLOP per ms = TFLOP/s
    keys = ("config", "engine", "precision", "batch", "p50_ms", "p90_ms", "per_sector_p50_ms")
    print("| " + " | ".join(str(r[k]) for k in keys) + f" | {tflops:.1f} | {r['peak_mem_mb']} |")
print("| eval (tiny, default, 100 sim scans) | L1 AP | L1 APH | L2 AP | L2 APH |")
print("|---|---|---|---|---|")
for precision in ("fp32", "bf16"):
    r = json.loads((out / f"eval_tiny_{precision}.json").read_text())
    row = [r[lv]["mean"][m] for lv in ("LEVEL_1", "LEVEL_2") for m in ("AP", "APH")]
    print(f"| {precision} | " + " | ".join(f"{v:.4f}" for v in row) + " |")
PY
