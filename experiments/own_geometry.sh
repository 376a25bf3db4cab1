#!/usr/bin/env bash
# Training from the rides' own geometry (--sfm-rounds) beside plain self-supervision, on the benchmark
# rendered at 512x128 (recipe_size.sh's data: 16 rides x 150 frames, seed 0, 12 training, 1 validation and
# 3 test towns), each evaluated on the 3 held-out towns: depth (abs_rel, a1, the scale's coefficient of
# variation over each ride) and the pose network's own odometry (snippet ATE, APE of whole rides). The
# budget covers the odometry of the training rides (RUN/rounds.json has each stage's time). Usage:
#
#   experiments/own_geometry.sh NAME SIZE MINUTES [cylsfm train flags and key=value overrides ...]
#   experiments/own_geometry.sh plain-256x64-15m 256x64 15
#   experiments/own_geometry.sh rounds1-256x64-15m 256x64 15 --sfm-rounds 1
#
# Results: experiments/out/NAME/{depth,pose}.json; experiments/own_geometry_table.py prints the table.
set -euo pipefail
cd "$(dirname "$0")/.."
name=$1; size=$2; minutes=$3; shift 3
bin=.venv/bin
out=experiments/out
data=$out/data512
. experiments/benchmark_data512.sh
run=$out/$name
if [ ! -f "$run/checkpoints/latest.pt" ]; then
  start=$SECONDS
  $bin/cylsfm train --data "$data" --out "$run" --size "$size" --minutes "$minutes" --no-progress "$@"
  echo $((SECONDS - start)) > "$run/wall_seconds"  # training and any odometry of the rounds
fi
$bin/cylsfm evaluate depth --checkpoint "$run" --data "$data" --split test --no-progress --json "$run/depth.json"
$bin/cylsfm evaluate pose --checkpoint "$run" --data "$data" --split test --no-progress --json "$run/pose.json"
