#!/usr/bin/env bash
# Training labels for the four real cameras from the training slice of the recorded minute (frames before
# 11:00:40; the rest is held out for evaluation), without manual labels: see training/autolabel.py.
# Needs the masks (calibrate.sh). Usage: autolabel.sh [FOOTAGE_DIR] [OUT_DIR]
set -euo pipefail
cd "$(dirname "$0")/../../.."
SITE=deploy/sites/state_ellsworth
FOOTAGE=${1:-../shared/data/state_ellsworth/sample_data}
OUT=${2:-out/autolabel}
for c in NE NW SE SW; do
  .venv/bin/roadside autolabel --frames "$FOOTAGE/gs_State_Ellsworth_$c" --masks $SITE/masks/$c.npz --camera $c \
      --until 11:00:40 --out "$OUT/$c" > /dev/null
done
cat "$OUT"/*/report.json
