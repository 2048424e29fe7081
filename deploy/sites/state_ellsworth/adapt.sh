#!/usr/bin/env bash
# The site-adapted detector: autolabel the training slice of the four real cameras (frames before
# 11:00:40), fine-tune the simulator-trained model on those labels mixed with simulator frames (so it keeps
# what it learned there), export to ONNX. No manual training labels.
# Starts from models/detector.pt (the shipped simulator-trained checkpoint) and keeps the loss it was trained with
# (recorded in the checkpoint; the shipped site model was adapted from run 5 with --beta-heading 0.05; adapted from
# run 11 this way it scored lower on the real frames, models/README.md).
# Usage: adapt.sh SIM_RECORDING [FOOTAGE_DIR] [MINUTES] [BASE]  (MINUTES: stage 1's budget, default 20)
#   SIM_RECORDING  a simulator recording of this site (roadside sim --site state_ellsworth --seconds 90 --hz 2 ...)
#   BASE           the checkpoint to adapt (default models/detector.pt); the shipped site model's: run 5,
#                  `git show 3343a09:models/detector.pt > out/run5.pt`, which records no loss settings: give its
#                  run's as TRAIN_FLAGS="--beta-heading 0.05" (a checkpoint that records them keeps them)
set -euo pipefail
cd "$(dirname "$0")/../../.."
SITE=deploy/sites/state_ellsworth
SIM=${1:?usage: adapt.sh SIM_RECORDING [FOOTAGE_DIR] [MINUTES] [BASE]}
FOOTAGE=${2:-../shared/data/state_ellsworth/sample_data}
MINUTES=${3:-20}
BASE=${4:-models/detector.pt}
read -r -a EXTRA <<< "${TRAIN_FLAGS:-}"  # more `roadside train` flags for both stages
[ -f $SITE/masks/SW.npz ] || bash $SITE/calibrate.sh
bash $SITE/autolabel.sh "$FOOTAGE" out/autolabel > /dev/null
COCO=()
for c in NE NW SE SW; do COCO+=(--coco out/autolabel/$c/labels.json --coco out/autolabel/$c/labels.json); done  # real x2
# Stage 1 (20 min, 1,274 steps for the shipped model), then stage 2 from its result at a lower learning rate
# (1,800 steps, 28 min): 50 min in all.
.venv/bin/roadside train --init "$BASE" "${COCO[@]}" --recording "$SIM" "${EXTRA[@]}" \
    --out out/train_state_ellsworth --overwrite --minutes "$MINUTES" --batch-size 12 --lr 5e-4 --seed 6
.venv/bin/roadside train --init out/train_state_ellsworth/model.pt "${COCO[@]}" --recording "$SIM" "${EXTRA[@]}" \
    --out out/train_state_ellsworth_2 --overwrite --steps 1800 --minutes 45 --batch-size 12 --lr 3e-4 --seed 7
.venv/bin/roadside export out/train_state_ellsworth_2/model.pt --out out/train_state_ellsworth_2/detector.onnx
