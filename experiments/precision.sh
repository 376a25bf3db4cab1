#!/usr/bin/env bash
# bf16 against fp32 on the demo's benchmark (256x64, its data and split): two seeds of each, the same
# number of steps, each model evaluated on the held-out towns with fp32 inference and with the networks in
# bf16. On a CPU without native bf16 the "true" runs are fp32 as well (the detection keeps fp32 there).
#
#   experiments/precision.sh [STEPS]     # default 1000 steps; results: experiments/out/amp-*/{depth,pose}-*.json
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-1000}
bin=.venv/bin
out=experiments/out
data=$out/data
. experiments/benchmark_data.sh
for seed in 0 1; do for amp in true false; do
  run=$out/amp-$amp-s$seed
  if [ ! -f "$run/checkpoints/latest.pt" ]; then
    $bin/cylsfm train --data "$data" --out "$run" --size 256x64 --no-progress --max-steps "$steps" --seed $seed amp=$amp
  fi
  for infer in fp32 auto; do
    flag=(); if [ $infer = fp32 ]; then flag=(--no-amp); fi
    $bin/cylsfm evaluate depth --checkpoint "$run" --data "$data" --split test --no-progress "${flag[@]}" --json "$run/depth-$infer.json" > /dev/null
    $bin/cylsfm evaluate pose --checkpoint "$run" --data "$data" --split test --no-progress "${flag[@]}" --json "$run/pose-$infer.json" > /dev/null
  done
done; done
$bin/python experiments/precision_table.py $out/amp-{true,false}-s{0,1}
