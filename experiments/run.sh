#!/usr/bin/env bash
# Train one configuration and evaluate it on the held-out towns of the benchmark: the commands behind each
# row of RESULTS.md. Usage:
#
#   experiments/run.sh NAME MINUTES [cylsfm train flags and key=value overrides ...]
#
# e.g.  experiments/run.sh improved-60 60
#       experiments/run.sh nowrap-60 60 --no-wrap
#       experiments/run.sh paper-60 60 --preset paper-synthia --size 256x64
#       experiments/run.sh equivariant-roll-60 60 --pose-head equivariant --roll
#
# The benchmark data (the demo's: 16 rides x 150 frames at 256x64, seed 0, split by sequence) is generated
# once into experiments/out/data. Results: experiments/out/NAME/{depth,pose,pose_yaw}.json and the run.
set -euo pipefail
cd "$(dirname "$0")/.."
name=$1; minutes=$2; shift 2
bin=.venv/bin
out=experiments/out
data=$out/data
if [ ! -f "$data/splits/default/test.txt" ]; then
  $bin/cylsfm synth "$data" --sequences 16 --frames 150 --width 256 --height 64 --seed 0 --overwrite
  $bin/python -c "from cylsfm.data.splits import make_splits; make_splits('$data', mode='sequence', fractions=(12/16, 1/16, 3/16), seed=0)"
fi
run=$out/$name
$bin/cylsfm train --data "$data" --out "$run" --size 256x64 --minutes "$minutes" --workers 1 --no-progress "$@"
$bin/cylsfm evaluate depth --checkpoint "$run" --data "$data" --split test --json "$run/depth.json"
$bin/cylsfm evaluate pose --checkpoint "$run" --data "$data" --split test --out "$run/trajectories" --json "$run/pose.json"
$bin/cylsfm evaluate pose --checkpoint "$run" --data "$data" --split test --yaw-roll 0 --json "$run/pose_yaw.json"
