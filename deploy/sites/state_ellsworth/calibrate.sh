#!/usr/bin/env bash
# Build the lookup masks of the four cameras from landmarks/*.json (one at a time; ~10 s each).
# Image circles (centre x, y, radius in px) were measured on the footage: see README.md.
set -euo pipefail
cd "$(dirname "$0")/../../.."
SITE=deploy/sites/state_ellsworth
for c in NE NW SE SW; do
  case $c in NE) C=646.5,471.7,518;; NW) C=612.5,480.4,539;; SE) C=661.2,483.1,515;; SW) C=639.6,475.1,517;; esac
  .venv/bin/roadside calibrate --landmarks $SITE/landmarks/$c.json --kind fisheye --image-circle $C --fov-deg 188 \
      --origin 42.22939632,-83.73899854,265 --out $SITE/masks/$c.npz --report $SITE/masks/$c.report.json
done
