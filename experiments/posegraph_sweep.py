"""The pose graph's uncertainties swept over rides already run by ``experiments/loops.py``: the command
behind RESULTS.md's rejected option "the pose graph's uncertainties tuned".

Usage::

    python experiments/posegraph_sweep.py OUT RIDE [RIDE ...]

``OUT`` is an output folder of ``experiments/loops.py`` (its ``odometry/RIDE`` runs and ``data``), each
``RIDE`` a name such as ``block-000``. Every ride's refined steps and verified loops are read from its
saved state (nothing is tracked or verified again) and closed by :func:`cylsfm.odometry.loops.graph.close_loops`
with each setting of a grid of :class:`~cylsfm.odometry.loops.graph.GraphSettings`; printed per setting:
the geometric mean and the largest of the rides' APE ratios (loops closed / refined), best first, and
today's defaults.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np

from cylsfm.data.io import read_tum
from cylsfm.evaluate.pose_metrics import chain_poses, trajectory_metrics
from cylsfm.odometry.loops import GraphSettings, close_loops
from cylsfm.odometry.state import STATE_FILE, State

GRID = {
    "step_rotation_deg": [0.1, 0.25, 1.0],
    "step_translation": [0.03, 0.1, 0.3],
    "step_scale": [0.002, 0.005, 0.02],
    "loop_translation": [0.3, 1.0, 3.0],
    "loop_rotation_deg": [0.3, 1.0],
}


def load(out: Path, name: str) -> tuple:
    route, town = name.rsplit("-", 1)
    state = State.load(out / "odometry" / name / STATE_FILE, None)
    if state is None:
        raise SystemExit(
            f"{out / 'odometry' / name}: no saved odometry state (run experiments/loops.py first)"
        )
    steps, loops = np.stack(state.refined).astype(np.float64), state.loops or []
    times, gt = read_tum(out / "data" / route / f"seq_{town}" / "poses.txt")
    base = trajectory_metrics(gt, times, chain_poses(steps), times)[0]["ape_rmse"]
    return steps, loops, gt, times, base


def ratios(rides: list[tuple], cfg: GraphSettings) -> list[float]:
    out = []
    for steps, loops, gt, times, base in rides:
        if any(lp.accepted for lp in loops):
            c2w, _ = close_loops(steps, loops, cfg)
            out.append(trajectory_metrics(gt, times, c2w, times)[0]["ape_rmse"] / base)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("rides", nargs="+")
    args = p.parse_args()
    rides = [load(args.out, name) for name in args.rides]
    table = []
    for values in itertools.product(*GRID.values()):
        r = ratios(rides, GraphSettings(**dict(zip(GRID, values, strict=True))))
        table.append((float(np.exp(np.mean(np.log(r)))), max(r), values, [round(x, 2) for x in r]))
    table.sort()
    print("geometric mean, largest, settings (" + ", ".join(GRID) + "), per ride")
    for row in table[:10]:
        print(row)
    r = ratios(rides, GraphSettings())
    print("today's defaults:", float(np.exp(np.mean(np.log(r)))), max(r), [round(x, 2) for x in r])


if __name__ == "__main__":
    main()
