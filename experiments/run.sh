#!/usr/bin/env bash
# Train one configuration and evaluate it on the held-out towns of the benchmark: the commands behind each
# row of RESULTS.md. Usage:
#
#   experiments/run.sh NAME [cylsfm train flags and key=value overrides ...]
#
# The flags must include the budget (--minutes M or --max-steps N), e.g.
#
#   experiments/run.sh improved-60 --minutes 60
#   experiments/run.sh nowrap --max-steps 7168 --no-wrap
#   experiments/run.sh paper --max-steps 1945 --preset paper-synthia
#   experiments/run.sh equivariant --max-steps 1945 --no-antisymmetric --pose-head equivariant
#
# A run that already exists is resumed (--resume) for the new budget, e.g. another 60 minutes:
#
#   cp -r experiments/out/improved-60 experiments/out/improved-120
#   experiments/run.sh improved-120 --minutes 60
#
# The benchmark data (the demo's: 16 rides x 150 frames at 256x64, seed 0, split by sequence: 12 training,
# 1 validation, 3 test towns) is generated once into experiments/out/data. Results:
# experiments/out/NAME/{depth,pose,pose_yaw}.json, the run itself and its trajectories.
set -euo pipefail
cd "$(dirname "$0")/.."
name=$1; shift
bin=.venv/bin
out=experiments/out
data=$out/data
. experiments/benchmark_data.sh
run=$out/$name
resume=()
if [ -f "$run/checkpoints/latest.pt" ]; then resume=(--resume); fi
$bin/cylsfm train --data "$data" --out "$run" --size 256x64 --no-progress "${resume[@]}" "$@"
$bin/cylsfm evaluate depth --checkpoint "$run" --data "$data" --split test --json "$run/depth.json"
$bin/cylsfm evaluate pose --checkpoint "$run" --data "$data" --split test --out "$run/trajectories" --json "$run/pose.json"
if [ "${ROLL_EVAL:-1}" = 1 ]; then  # ROLL_EVAL=0: no evaluation on rolled rides
  $bin/cylsfm evaluate pose --checkpoint "$run" --data "$data" --split test --yaw-roll 0 --json "$run/pose_yaw.json"
fi
