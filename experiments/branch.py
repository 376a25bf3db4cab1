"""Branch a training run at one of its checkpoints with some settings changed.

    python experiments/branch.py experiments/out/default-120/checkpoints/step_0008000.pt \
        experiments/out/NEW loss.ssim_weight=0.5
    experiments/run.sh NEW --minutes 43.2     # resumes the branch for the rest of the budget

A setting that only takes effect from a step after the checkpoint's (e.g. a loss term switched on at that
step) makes the branch the run that the changed recipe gives from the start: training at a fixed seed is
deterministic and a resumed run continues exactly (networks, optimiser, data order). The new run gets the
checkpoint as its latest.pt and the changed configuration in its config.yaml.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cylsfm.model.checkpoint import load_checkpoint, save_checkpoint
from cylsfm.model.config import apply_overrides, config_from_dict, config_to_dict, save_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", help="a run's step_NNNNNNN.pt (or latest.pt)")
    ap.add_argument("run", help="the new run directory (must not exist)")
    ap.add_argument("overrides", nargs="+", help="key=value settings to change")
    args = ap.parse_args()
    run = Path(args.run)
    if run.exists():
        raise SystemExit(f"{run}: already exists")
    state = load_checkpoint(args.checkpoint)
    state.pop("path", None)
    state.pop("format", None)
    cfg = apply_overrides(config_from_dict(state["config"], "checkpoint config", saved=True), args.overrides)
    state["config"] = config_to_dict(cfg)
    (run / "checkpoints").mkdir(parents=True)
    save_checkpoint(run / "checkpoints" / "latest.pt", state)
    save_config(cfg, run / "config.yaml")
    print(f"{run}: branched at step {state['step']} with {' '.join(args.overrides)}")


if __name__ == "__main__":
    main()
