#!/usr/bin/env bash
# Reproduces the shipped default model from scratch: trains `tiny` on the simulator, evaluates it on the
# 200 held-out simulated scans (stream 7) and copies the weights to model/weights/tiny-sim.pt.
# Usage: bash scripts/train_default.sh [RUN_DIR]   (default runs/default; an interrupted run resumes)
# Environment: STEPS (default 3900), BATCH (2 scans per step), LR (2e-3), DEVICE (auto), WORKERS (1),
# THREADS (0 = torch default).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
PHIM="${PHIM_VENV:-.venv}/bin/phim"
RUN=${1:-runs/default}
STEPS=${STEPS:-3900}
RESUME=()
if [ -f "$RUN/state.pt" ]; then RESUME=(--resume); fi
"$PHIM" train --config tiny --data sim --seed 0 --steps "$STEPS" --batch-size "${BATCH:-2}" \
  --lr "${LR:-2e-3}" --out "$RUN" \
  --device "${DEVICE:-auto}" --workers "${WORKERS:-1}" --threads "${THREADS:-0}" "${RESUME[@]}"
"$PHIM" eval --checkpoint "$RUN/model.pt" --data sim --scans 200 --seed 7 --json \
  --predictions "$RUN/predictions-sim-seed7.npz" | tee "$RUN/eval-sim-seed7.json"
mkdir -p model/weights
cp "$RUN/model.pt" model/weights/tiny-sim.pt
echo "default model: model/weights/tiny-sim.pt ($(du -h model/weights/tiny-sim.pt | cut -f1)); metrics: $RUN/eval-sim-seed7.json"
