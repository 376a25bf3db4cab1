#!/usr/bin/env bash
# The paper's field-of-view table repeated with `cylsfm odometry --refine`: each run of experiments/fov.sh
# (the same data, recipe and steps at 360, 270, 180 and 100 degrees) follows the 3 held-out test rides
# whole, refined by direct alignment with its own depth on its own crop, and one table shows the refined
# trajectory, the pose network alone and constant velocity per field of view, the visual compass beside the
# full panorama. Usage:
#
#   experiments/fov_odometry.sh STEPS      # after experiments/fov.sh STEPS
#
# Results: experiments/out/fov-DEG-STEPS/odometry/{refine/SEQ/,table.json}; the table is printed.
set -euo pipefail
cd "$(dirname "$0")/.."
steps=$1
runs=()
for fov in 360 270 180 100; do
  run=experiments/out/fov-$fov-$steps
  if [ ! -f "$run/odometry/table.json" ]; then
    .venv/bin/python experiments/odometry.py "$run" "$run/odometry" refine
  fi
  runs+=("$run/odometry/table.json:${fov} degrees")
done
.venv/bin/python experiments/fov_odometry_table.py "${runs[@]}"
