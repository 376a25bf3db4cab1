# Sourced by the experiment scripts that train at several sizes: the benchmark rendered at 512x128 (16 rides x
# 150 frames, seed 0, the demo's split by town: 12 training, 1 validation, 3 test), generated once into $data.
# Needs $bin (the virtual environment's bin folder) and $data.
if [ ! -f "$data/splits/default/test.txt" ]; then
  $bin/cylsfm synth "$data" --sequences 16 --frames 150 --width 512 --height 128 --seed 0 --overwrite
  $bin/python -c "from cylsfm.data.splits import make_splits; make_splits('$data', mode='sequence', fractions=(12/16, 1/16, 3/16), seed=0)"
fi
