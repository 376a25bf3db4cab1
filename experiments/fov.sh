#!/usr/bin/env bash
# The paper's field-of-view experiment (Table 2) on the benchmark: the same data, recipe and number of
# steps at 360, 270, 180 and 100 degrees of horizontal field of view (a centred crop of each panorama; no
# wrap-around below 360), each evaluated on the held-out towns, then one table with constant velocity
# beside every row and the visual compass beside the full panorama. Usage:
#
#   experiments/fov.sh STEPS [cylsfm train flags and key=value overrides ...]
#
# e.g. `experiments/fov.sh 1000`. The pose network alone is compared (no compass: it needs the whole
# circle). With the default recipe the full panorama gets the yaw-equivariant head and the crops the
# paper's averaged head (the equivariant one rotates columns by their azimuths on the full circle).
# Runs go to experiments/out/fov-DEG-STEPS (resumed when they exist); the table is printed at the end.
set -euo pipefail
cd "$(dirname "$0")/.."
steps=$1; shift
runs=()
for fov in 360 270 180 100; do
  name=fov-$fov-$steps
  ROLL_EVAL=0 experiments/run.sh "$name" --max-steps "$steps" --fov "$fov" --no-compass "$@"
  runs+=("experiments/out/$name:${fov} degrees")
done
.venv/bin/python experiments/tables.py "${runs[@]}"
.venv/bin/python experiments/fov_table.py "${runs[@]}"
