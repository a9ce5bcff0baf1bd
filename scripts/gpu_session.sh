#!/usr/bin/env bash
# On a GPU machine whose python3 holds a CUDA build of torch and the project's other dependencies
# (pip install ".[server]" without touching torch; the stages tests and train need only the model's:
# msgspec, click, numba, matplotlib, rich): the GPU checks and timings of docs/benchmarks.md, in
# stages that each fit a 10-minute call, one process at a time (timings taken beside another GPU or compile
# job are worthless, and a paper compile takes ~1 minute per bucket on 16 host cores).
# Needs the KITTI scans 000000-000005 at ../shared/data/kitti_object/velodyne (or $PHIM_SAMPLES_DIR).
# Usage: bash scripts/gpu_session.sh OUTDIR STAGE...   (with 15 minutes of device time: `bench profile`, then
# `tests server_paper`; the profile after the bench finds the bench's kernels in inductor's cache)
#   tests    tests/test_cuda.py (parity: kernels, eager, fixed and compiled graph step, bf16)    ~6 min cold
#   profile  paper graph step, batch 1, bf16 then fp32: wall time against kernel time, top kernels; the
#            shipped refiner for a batch of 32 streams (host lookups, one PointNet forward)          ~3 min
#   bench    phim bench model: paper eager, and graph (crops) in bf16 at batch 1 and 8             ~8 min
#   bench2   tiny graph at batch 1 and 8; paper graph bf16 batch 8 on the whole map (--whole-map)  ~7 min
#   server   tiny (shipped) served by the graph engine, bf16, max batch 32: zenoh closed-loop sweep 1..64
#            vehicles, then open loop at sensor rate (compiles 6 batch buckets first, each on the
#            whole map and on crops)                                                             ~8 min
#   server_paper  the same for `paper` (random weights: throughput only), max batch 8, sweep 1,4,8,16 ~9 min
#   eval     the shipped model's accuracy in fp32 and bf16 on the GPU                              ~2 min
#   train    the shipped model's next training phase on the simulator, 8 minutes, into OUTDIR/train;
#            TRAIN_FROM=<that folder, carried back> resumes it (TRAIN_STEPS 20000 of batch TRAIN_BATCH 8
#            at TRAIN_LR 1e-3, TRAIN_WORKERS 12 simulator processes, TRAIN_DEVICE cuda)         ~9 min
#   refine   the default's two refiner stages (scripts/train_default.sh's recipe: REFINE_SCANS 800 of
#            streams 28 and 29) on the host's CPUs, fitted to REFINE_FROM (OUTDIR/train/model.pt) with
#            REFINE_WORKERS (16) processes reading the scans, into OUTDIR/refined.pt      ~5 min (not yet timed)
# SERVE_CONFIG (tiny), SERVE_MAX_BATCH (32), SERVE_DEVICE (cuda), SERVE_ENGINE (graph), SERVE_PRECISION
# (bf16) and SWEEP (1,4,16,64) change the server stage, e.g. to try it on a CPU.
# Every step has a time limit; OUTDIR/steps.txt says how each ended, and the table comes last.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: gpu_session.sh OUTDIR STAGE...}
shift
mkdir -p "$out"
py=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
points=32768 # every KITTI 1/4 sector (26-33k points) pads to one bucket: one compile per run

step() { # NAME SECONDS COMMAND...: stdout to OUTDIR/NAME.out, stderr to NAME.err
    local name=$1 limit=$2 t0=$SECONDS
    shift 2
    timeout "$limit" "$@" >"$out/$name.out" 2>"$out/$name.err"
    local rc=$?
    echo "$name rc=$rc $((SECONDS - t0))s" | tee -a "$out/steps.txt"
}
bench() { # CONFIG BATCH ENGINE PRECISION SECONDS [--whole-map]: a graph run compiles the whole map's
    # bucket in its first warm-up turn and the crops' in the second
    step "bench_$1_b$2_$3_$4${6:-}" "$5" "$py" -m phim bench model --config "$1" --batch "$2" --engine "$3" \
        --precision "$4" --device cuda --turns 10 --sector-points $points --json ${6:-}
}

serve_and_sweep() { # the worker as deployed, driven over zenoh by the load tester on the same host
    local dev=${SERVE_DEVICE:-cuda} engine=${SERVE_ENGINE:-graph} sweep=${SWEEP:-1,4,16,64} t0=$SECONDS
    local tag=${SERVE_CONFIG:-tiny}
    "$py" -m phim serve --config "$tag" --device "$dev" --engine "$engine" --precision "${SERVE_PRECISION:-bf16}" \
        --max-batch "${SERVE_MAX_BATCH:-32}" --max-streams 128 --queue-size 256 --port 18080 \
        --zenoh-listen tcp/127.0.0.1:17447 >"$out/serve_$tag.log" 2>&1 &
    local pid=$!
    until curl -sf localhost:18080/health/ready >/dev/null; do
        sleep 2
        if ! kill -0 $pid 2>/dev/null || ((SECONDS - t0 > 420)); then
            echo "server not ready after $((SECONDS - t0))s" | tee -a "$out/steps.txt"
            kill $pid 2>/dev/null
            return
        fi
    done
    echo "server ready rc=0 $((SECONDS - t0))s" | tee -a "$out/steps.txt"
    local client=(--transport zenoh --zenoh-connect tcp/127.0.0.1:17447 --url http://127.0.0.1:18080 --synthetic
        --warmup 2 --duration 8 --keep-going --no-progress)
    step "loadtest_${tag}_closed" 200 "$py" -m phim loadtest "${client[@]}" --mode closed --sweep "$sweep" --json
    step "loadtest_${tag}_open" 200 "$py" -m phim loadtest "${client[@]}" --mode open --sweep "$sweep" --json
    kill -TERM $pid
    wait $pid
    "$py" - "$out" "$tag" <<'PY'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
for f in sorted(out.glob(f"loadtest_{sys.argv[2]}_*.out")):
    try:
        r = json.loads(f.read_text())
    except ValueError:
        continue
    for s in r["steps"]:
        keys = ("vehicles", "achieved_sectors_per_s", "p50_ms", "p99_ms", "server_model_p50_ms", "send_lag_p99_ms")
        print(f.stem, {k: s[k] for k in keys + ("sent", "answered", "errors", "lost")})
PY
}

{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || echo "no GPU"; } | tee "$out/gpu.txt"
"$py" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" | tee -a "$out/gpu.txt"
for stage in "$@"; do
    case $stage in
    tests)
        step test_cuda 480 "$py" -m pytest -q -p no:cacheprovider tests/test_cuda.py
        tail -15 "$out/test_cuda.out"
        ;;
    profile)
        for precision in bf16 fp32; do
            step "profile_paper_$precision" 240 env PYTHONPATH=. "$py" scripts/profile_step.py --config paper \
                --device cuda --engine graph --precision $precision --sector-points $points \
                --json "$out/profile_paper_$precision.json"
            cat "$out/profile_paper_$precision.out"
        done
        step refiner_b32 90 "$py" -m phim bench refiner --device cuda --streams 32 --repeats 20
        cat "$out/refiner_b32.out"
        ;;
    bench)
        bench paper 1 eager fp32 60
        bench paper 1 graph bf16 240
        bench paper 8 graph bf16 270
        ;;
    bench2)
        bench tiny 1 graph fp32 120
        bench tiny 8 graph fp32 120
        bench paper 8 graph bf16 240 --whole-map
        ;;
    server)
        serve_and_sweep
        ;;
    server_paper)
        SERVE_CONFIG=paper SERVE_MAX_BATCH=8 SWEEP=${SWEEP:-1,4,8,16} serve_and_sweep
        ;;
    eval)
        for precision in fp32 bf16; do
            step "eval_tiny_$precision" 120 "$py" -m phim eval --checkpoint default --data sim --scans 100 \
                --device cuda --precision $precision --json
        done
        ;;
    train)
        run=$out/train
        if [ -n "${TRAIN_FROM:-}" ] && [ ! -e "$run" ]; then cp -r "$TRAIN_FROM" "$run"; fi
        resume=()
        if [ -f "$run/state.pt" ]; then resume=(--resume); fi
        step train 570 "$py" -m phim train --config tiny --data sim --device "${TRAIN_DEVICE:-cuda}" \
            --batch-size "${TRAIN_BATCH:-8}" --workers "${TRAIN_WORKERS:-12}" --seed "${TRAIN_SEED:-22}" \
            --steps "${TRAIN_STEPS:-20000}" --lr "${TRAIN_LR:-1e-3}" --direction-weight 1.0 \
            --init "${TRAIN_INIT:-default}" --out "$run" --max-minutes "${TRAIN_MINUTES:-8}" --no-progress \
            "${resume[@]}"
        tail -2 "$run/metrics.csv"
        ;;
    refine)
        recipe=(--seed 28 --seed 29 --scans "${REFINE_SCANS:-800}" --epochs 8 --points 64 --fit-every-cell cyclist
            --workers "${REFINE_WORKERS:-16}")
        step refine1 290 "$py" -m phim train-refiner --checkpoint "${REFINE_FROM:-$out/train/model.pt}" \
            --out "$out/refined1.pt" --stages 1 "${recipe[@]}"
        step refine2 290 "$py" -m phim train-refiner --checkpoint "$out/refined1.pt" --keep --stages 2 \
            --out "$out/refined.pt" "${recipe[@]}"
        ;;
    *) echo "unknown stage $stage" >&2 && exit 2 ;;
    esac
done
"$py" - "$out" <<'PY'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
print(open(out / "gpu.txt").read().strip())
# one streaming step, whole map / crops (torch.utils.flop_counter on the fixed step, docs/benchmarks.md)
step_gflops = {("paper", False): 739.3, ("paper", True): 377.5, ("tiny", False): 1.24, ("tiny", True): 0.99}
rows = []
for f in sorted(out.glob("bench_*.out")):
    try:
        r = json.loads(f.read_text())
    except ValueError:
        continue  # the step failed: steps.txt says how
    tflops = step_gflops[r["config"], r["bev_crop"]] * r["batch"] / r["p50_ms"]  # GFLOP per ms = TFLOP/s
    keys = ("config", "engine", "bev_crop", "precision", "batch", "p50_ms", "p90_ms", "peak_mem_mb")
    rows.append("| " + " | ".join(str(r[k]) for k in keys) + f" | {r['batch'] * 1e3 / r['p50_ms']:.0f} | {tflops:.1f} |")
if rows:
    print("| config | engine | crops | precision | streams | p50 ms | p90 ms | peak MB | sectors/s | TFLOP/s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
for f in sorted(out.glob("eval_tiny_*.out")):
    try:
        r = json.loads(f.read_text())
    except ValueError:
        continue
    print(f.stem, {lv: {m: round(r[lv]["mean"][m], 4) for m in ("AP", "APH")} for lv in ("LEVEL_1", "LEVEL_2")})
PY
cat "$out/steps.txt"
