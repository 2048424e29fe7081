#!/usr/bin/env bash
# Training images for the four real cameras without manual labels: simulated vehicles drawn over each camera's
# median background of the training slice (frames before 11:00:40), on the lanes where autolabel saw vehicles
# move (see training/composite.py). Needs the masks (calibrate.sh) and the autolabel labels (autolabel.sh).
# Usage: composite.sh [FOOTAGE_DIR] [AUTOLABEL_DIR] [OUT_DIR]
set -euo pipefail
cd "$(dirname "$0")/../../.."
SITE=deploy/sites/state_ellsworth
FOOTAGE=${1:-../shared/data/state_ellsworth/sample_data}
LABELS=${2:-out/autolabel}
OUT=${3:-out/composite}
for c in NE NW SE SW; do
  .venv/bin/roadside composite --frames "$FOOTAGE/gs_State_Ellsworth_$c" --masks $SITE/masks/$c.npz --camera $c \
      --until 11:00:40 --placements "$LABELS/$c/labels.json" --out "$OUT/$c" --seconds 100 --hz 1 --seed 21 \
      --teacher models/detector_state_ellsworth_fp32.onnx > /dev/null
done
cat "$OUT"/*/report.json
