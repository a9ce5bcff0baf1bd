#!/usr/bin/env bash
# Reproduces the shipped default model from scratch: trains `tiny` on the simulator (3,900 steps on sim
# stream 0), fine-tunes it twice (2,600 steps on stream 1, then 3,000 steps on stream 2; lower peak learning
# rate, direction loss weight 1), evaluates the result on the 200 held-out simulated scans (stream 7) and
# copies it to model/weights/tiny-sim.pt.
# Usage: bash scripts/train_default.sh [RUN_DIR]   (default runs/default; an interrupted phase resumes;
# the fine-tunes go to RUN_DIR/finetune and RUN_DIR/finetune2)
# Environment: STEPS (3900), FT_STEPS (2600), FT2_STEPS (3000), BATCH (2 scans per step), LR (2e-3),
# FT_LR (1e-3), DEVICE (auto), WORKERS (1), THREADS (0 = torch default).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
PHIM="${PHIM_VENV:-.venv}/bin/phim"
RUN=${1:-runs/default}
FT="$RUN/finetune"
FT2="$RUN/finetune2"
common=(--config tiny --data sim --batch-size "${BATCH:-2}" --device "${DEVICE:-auto}"
  --workers "${WORKERS:-1}" --threads "${THREADS:-0}")
resume_flag() { if [ -f "$1/state.pt" ]; then echo --resume; fi; }
# shellcheck disable=SC2046  # resume_flag prints nothing or one word
"$PHIM" train "${common[@]}" --seed 0 --steps "${STEPS:-3900}" --lr "${LR:-2e-3}" \
  --out "$RUN" $(resume_flag "$RUN")
# shellcheck disable=SC2046
"$PHIM" train "${common[@]}" --seed 1 --steps "${FT_STEPS:-2600}" --lr "${FT_LR:-1e-3}" \
  --direction-weight 1.0 --init "$RUN/model.pt" --out "$FT" $(resume_flag "$FT")
# shellcheck disable=SC2046
"$PHIM" train "${common[@]}" --seed 2 --steps "${FT2_STEPS:-3000}" --lr "${FT_LR:-1e-3}" \
  --direction-weight 1.0 --init "$FT/model.pt" --out "$FT2" $(resume_flag "$FT2")
"$PHIM" eval --checkpoint "$FT2/model.pt" --data sim --scans 200 --seed 7 --json \
  --predictions "$FT2/predictions-sim-seed7.npz" | tee "$FT2/eval-sim-seed7.json"
mkdir -p model/weights
cp "$FT2/model.pt" model/weights/tiny-sim.pt
echo "default model: model/weights/tiny-sim.pt ($(du -h model/weights/tiny-sim.pt | cut -f1));" \
  "metrics: $FT2/eval-sim-seed7.json"
