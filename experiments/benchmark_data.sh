# Sourced by the experiment scripts: the benchmark data (the demo's: 16 rides x 150 frames at 256x64,
# seed 0, split by sequence: 12 training, 1 validation, 3 test towns), generated once into $data.
# Needs $bin (the virtual environment's bin folder) and $data.
if [ ! -f "$data/splits/default/test.txt" ]; then
  $bin/cylsfm synth "$data" --sequences 16 --frames 150 --width 256 --height 64 --seed 0 --overwrite
  $bin/python -c "from cylsfm.data.splits import make_splits; make_splits('$data', mode='sequence', fractions=(12/16, 1/16, 3/16), seed=0)"
fi
