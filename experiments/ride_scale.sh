#!/usr/bin/env bash
# A trained run's depth in each test ride's one scale: `cylsfm odometry --refine --depth` (with the bundle
# adjustment, which brings every frame's depth to the adjusted points) over each held-out ride of the
# 512x128 benchmark (recipe_size.sh's data), then `cylsfm evaluate depth` of those depth files: the
# scale's coefficient of variation over each ride beside the network's own (RUN/depth.json). Usage:
#
#   experiments/ride_scale.sh experiments/out/plain-256x64-30m
#
# Results: RUN/rides/SEQ/ (the odometry: trajectory, metrics.json, depth/), RUN/depth_rides.json.
set -euo pipefail
cd "$(dirname "$0")/.."
run=$1
bin=.venv/bin
data=experiments/out/data512
for seq in $(grep -v '^#' "$data/splits/default/test.txt" | cut -d' ' -f1 | sort -u); do
  $bin/cylsfm odometry "$data/$seq" --checkpoint "$run" --out "$run/rides/$seq" --refine --depth --no-progress
done
$bin/cylsfm evaluate depth --predictions "$run/rides" --data "$data" --split test --no-progress \
  --json "$run/depth_rides.json"
