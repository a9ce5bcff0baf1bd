#!/usr/bin/env bash
# Reproduces the shipped default model from scratch: trains `tiny` on the simulator (3,900 steps on sim
# stream 0), fine-tunes it (2,600 steps on stream 1, lower peak learning rate, direction loss weight 1),
# evaluates the result on the 200 held-out simulated scans (stream 7) and copies it to
# model/weights/tiny-sim.pt.
# Usage: bash scripts/train_default.sh [RUN_DIR]   (default runs/default; an interrupted phase resumes;
# the fine-tune goes to RUN_DIR/finetune)
# Environment: STEPS (3900), FT_STEPS (2600), BATCH (2 scans per step), LR (2e-3), FT_LR (1e-3),
# DEVICE (auto), WORKERS (1), THREADS (0 = torch default).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
PHIM="${PHIM_VENV:-.venv}/bin/phim"
RUN=${1:-runs/default}
FT="$RUN/finetune"
common=(--config tiny --data sim --batch-size "${BATCH:-2}" --device "${DEVICE:-auto}"
  --workers "${WORKERS:-1}" --threads "${THREADS:-0}")
resume_flag() { if [ -f "$1/state.pt" ]; then echo --resume; fi; }
# shellcheck disable=SC2046  # resume_flag prints nothing or one word
"$PHIM" train "${common[@]}" --seed 0 --steps "${STEPS:-3900}" --lr "${LR:-2e-3}" \
  --out "$RUN" $(resume_flag "$RUN")
# shellcheck disable=SC2046
"$PHIM" train "${common[@]}" --seed 1 --steps "${FT_STEPS:-2600}" --lr "${FT_LR:-1e-3}" \
  --direction-weight 1.0 --init "$RUN/model.pt" --out "$FT" $(resume_flag "$FT")
"$PHIM" eval --checkpoint "$FT/model.pt" --data sim --scans 200 --seed 7 --json \
  --predictions "$FT/predictions-sim-seed7.npz" | tee "$FT/eval-sim-seed7.json"
mkdir -p model/weights
cp "$FT/model.pt" model/weights/tiny-sim.pt
echo "default model: model/weights/tiny-sim.pt ($(du -h model/weights/tiny-sim.pt | cut -f1));" \
  "metrics: $FT/eval-sim-seed7.json"
