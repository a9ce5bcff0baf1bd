#!/usr/bin/env bash
# Reproduces the shipped default model from scratch: trains `tiny` on the simulator (3,900 steps on sim
# stream 0), fine-tunes it eighteen times (2,600 steps on stream 1, 3,000 on stream 2, 6,000 on stream 4,
# 4,000 on stream 5, 2,500 on stream 8, 1,600 on stream 9, 2,500 on streams 12, 13, 14, 15, 16, 17, 18 and
# 19, then 1,200 steps of 4 scans on streams 21 and 23, then 2,500 steps on streams 31 and 36; lower peak
# learning rate, half that in the last thirteen, direction loss weight 1), trains the box refiner on the last phase's
# boxes (800 scans each of streams 28 and 29, 8 epochs, 64 points a box, with its context layer and flip
# output: `phim train-refiner`) and its second stage on the first stage's boxes (`--keep`), evaluates the
# result on the 200 held-out simulated scans (stream 7) and copies it to model/weights/tiny-sim.pt. `tiny`
# reads x, y, z; the shipped weights' phases 1-8 read intensity too and phases 9-19 left it out
# (docs/model-card.md).
# Usage: bash scripts/train_default.sh [RUN_DIR]   (default runs/default; an interrupted phase resumes;
# the fine-tunes go to RUN_DIR/finetune, RUN_DIR/finetune2, ... RUN_DIR/finetune18)
# Environment: STEPS (3900), FT_STEPS (2600), FT2_STEPS (3000), FT3_STEPS (6000), FT4_STEPS (4000),
# FT5_STEPS (2500), FT6_STEPS (1600), FT7_STEPS (2500), FT8_STEPS (2500), FT9_STEPS (2500), FT10_STEPS (2500),
# FT11_STEPS (2500), FT12_STEPS (2500), FT13_STEPS (2500), FT14_STEPS (2500), FT15_STEPS (1200),
# FT16_STEPS (1200), FT17_STEPS (2500), FT18_STEPS (2500), BATCH (2 scans per step; phases 16-17 take 4:
# `quad` below), LR (2e-3), FT_LR (1e-3), DEVICE (auto), WORKERS (1 per process), THREADS (0 = torch default).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
PHIM="${PHIM_VENV:-.venv}/bin/phim"
PHIM_PY="${PHIM_VENV:-.venv}/bin/python"
RUN=${1:-runs/default}
common=(--config tiny --data sim --batch-size "${BATCH:-2}" --device "${DEVICE:-auto}"
  --workers "${WORKERS:-1}" --threads "${THREADS:-0}")

# phase OUT_DIR SEED STEPS LR [more phim train flags]: one training phase, resumed if it was interrupted, started
# by $launch (empty: one process)
launch=()
phase() {
  local out=$1 seed=$2 steps=$3 lr=$4
  shift 4
  local resume=()
  if [ -f "$out/state.pt" ]; then resume=(--resume); fi
  "${launch[@]}" "$PHIM" train "${common[@]}" --seed "$seed" --steps "$steps" --lr "$lr" --out "$out" "$@" \
    "${resume[@]}"
}

# quad: a phase of 4 scans a step. On a CPU two DDP processes (torchrun, gloo) of 2 scans and one thread each:
# the same 4 scans a step at ~1.1x the scans/s of one process on the 2-core machine (docs/benchmarks.md).
# On a GPU one process of 4. The last --batch-size and --threads win over common's.
if [ "${DEVICE:-auto}" = cpu ] || ! "$PHIM_PY" -c 'import sys, torch; sys.exit(not torch.cuda.is_available())'; then
  quad_launch=("${PHIM_VENV:-.venv}/bin/torchrun" --standalone --nproc_per_node 2 --no-python)
  quad_flags=(--batch-size 2 --threads 1)
else
  quad_launch=()
  quad_flags=(--batch-size 4)
fi
quad() {
  local launch=("${quad_launch[@]}")
  phase "$@" "${quad_flags[@]}"
}

tune=(--direction-weight 1.0)
four=(--point-features 4)  # phases 1-8 read intensity too; finetune8 starts without its weights
phase "$RUN" 0 "${STEPS:-3900}" "${LR:-2e-3}" "${four[@]}"
phase "$RUN/finetune" 1 "${FT_STEPS:-2600}" "${FT_LR:-1e-3}" "${tune[@]}" --init "$RUN/model.pt" "${four[@]}"
phase "$RUN/finetune2" 2 "${FT2_STEPS:-3000}" "${FT_LR:-1e-3}" "${tune[@]}" --init "$RUN/finetune/model.pt" "${four[@]}"
phase "$RUN/finetune3" 4 "${FT3_STEPS:-6000}" "${FT_LR:-1e-3}" "${tune[@]}" --init "$RUN/finetune2/model.pt" "${four[@]}"
phase "$RUN/finetune4" 5 "${FT4_STEPS:-4000}" "${FT_LR:-1e-3}" "${tune[@]}" --init "$RUN/finetune3/model.pt" "${four[@]}"
phase "$RUN/finetune5" 8 "${FT5_STEPS:-2500}" "${FT_LR:-1e-3}" "${tune[@]}" --init "$RUN/finetune4/model.pt" "${four[@]}"
phase "$RUN/finetune6" 9 "${FT6_STEPS:-1600}" 5e-4 "${tune[@]}" --init "$RUN/finetune5/model.pt" "${four[@]}"
phase "$RUN/finetune7" 12 "${FT7_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune6/model.pt" "${four[@]}"
phase "$RUN/finetune8" 13 "${FT8_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune7/model.pt"
phase "$RUN/finetune9" 14 "${FT9_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune8/model.pt"
phase "$RUN/finetune10" 15 "${FT10_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune9/model.pt"
phase "$RUN/finetune11" 16 "${FT11_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune10/model.pt"
phase "$RUN/finetune12" 17 "${FT12_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune11/model.pt"
phase "$RUN/finetune13" 18 "${FT13_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune12/model.pt"
phase "$RUN/finetune14" 19 "${FT14_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune13/model.pt"
quad "$RUN/finetune15" 21 "${FT15_STEPS:-1200}" 5e-4 "${tune[@]}" --init "$RUN/finetune14/model.pt"
quad "$RUN/finetune16" 23 "${FT16_STEPS:-1200}" 5e-4 "${tune[@]}" --init "$RUN/finetune15/model.pt"
# phase 18: the simulator's world of objects made of parts (checkpoints/newworld-ft1)
phase "$RUN/finetune17" 31 "${FT17_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune16/model.pt"
# phase 19: pedestrians in groups and beside street furniture, concrete barriers (checkpoints/company-ft1)
phase "$RUN/finetune18" 36 "${FT18_STEPS:-2500}" 5e-4 "${tune[@]}" --init "$RUN/finetune17/model.pt"
# the refiner: its first stage on phase 18's boxes, then (--keep) the second on the first stage's boxes; each
# reads the points in its boxes grown by the class's margin (RefineConfig.grow: 1 m, pedestrians 0.4 m) and
# learns from the heatmaps' local maxima and every cell of a cyclist's heatmap (--fit-every-cell)
LAST="$RUN/refined"
mkdir -p "$RUN/refined1" "$LAST"
refiner=(--seed 28 --seed 29 --scans 800 --epochs 8 --points 64 --fit-every-cell cyclist --threads "${THREADS:-0}")
if [ ! -f "$RUN/refined1/model.pt" ]; then
  "$PHIM" train-refiner --checkpoint "$RUN/finetune18/model.pt" --out "$RUN/refined1/model.pt" --stages 1 \
    "${refiner[@]}"
fi
if [ ! -f "$LAST/model.pt" ]; then
  "$PHIM" train-refiner --checkpoint "$RUN/refined1/model.pt" --keep --stages 2 --out "$LAST/model.pt" \
    "${refiner[@]}"
fi
"$PHIM" eval --checkpoint "$LAST/model.pt" --data sim --scans 200 --seed 7 --json \
  --predictions "$LAST/predictions-sim-seed7.npz" | tee "$LAST/eval-sim-seed7.json"
mkdir -p model/weights
cp "$LAST/model.pt" model/weights/tiny-sim.pt
echo "default model: model/weights/tiny-sim.pt ($(du -h model/weights/tiny-sim.pt | cut -f1));" \
  "metrics: $LAST/eval-sim-seed7.json"
