#!/usr/bin/env bash
# The README's own-footage recipe (the default preset, a wall-clock budget) trained at one size on the
# benchmark rendered at 512x128 (16 rides x 150 frames, seed 0, the demo's split by town: 12 training,
# 1 validation, 3 test), and evaluated on the 3 held-out towns: depth (with the scale's steadiness over
# each ride), ego-motion over snippets and whole rides. Frames are resampled to the training size by the
# loader, so every size trains on the same pixels. Usage:
#
#   experiments/recipe_size.sh 512x128 120 [SEED]     # results: experiments/out/recipe-512x128-120m-s0/
#   experiments/recipe_size.sh 256x64 120
set -euo pipefail
cd "$(dirname "$0")/.."
size=$1; minutes=$2; seed=${3:-0}
bin=.venv/bin
out=experiments/out
data=$out/data512
. experiments/benchmark_data512.sh
run=$out/recipe-$size-${minutes}m-s$seed
if [ ! -f "$run/checkpoints/latest.pt" ]; then
  $bin/cylsfm train --data "$data" --out "$run" --size "$size" --minutes "$minutes" --seed "$seed" --no-progress
fi
$bin/cylsfm evaluate depth --checkpoint "$run" --data "$data" --split test --no-progress --json "$run/depth.json"
$bin/cylsfm evaluate pose --checkpoint "$run" --data "$data" --split test --no-progress --json "$run/pose.json"
