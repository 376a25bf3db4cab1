"""The camera height in the pose graph: each frame's fitted ground height as a soft factor on its scale,
against the steps' lengths divided by it (``--steady-height``), from the states ``experiments/loops.py``
left behind.

Usage::

    python experiments/loops_height.py OUT [OUT ...] [--sigmas 0.02 0.05 0.1]

For each closed or out-and-back ride of each ``OUT``: APE (Sim(3), m) of the plain refinement without and
with its loops, of ``--steady-height``'s steps (:func:`~cylsfm.geometry.ground.steady_height_steps`)
without and with them, and of the pose graph with a height factor on every frame's scale (standard
deviation ``sigma`` in log) without and with them. Nothing is run again.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from loops_errors import ape, load

from cylsfm.evaluate.pose_metrics import chain_poses
from cylsfm.geometry.ground import steady_height_steps
from cylsfm.odometry.posegraph import GraphSettings, close_loops


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("outs", type=Path, nargs="+")
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.02, 0.05, 0.1])
    args = parser.parse_args()
    head = ["plain", "steady"] + [f"factor {s}" for s in args.sigmas]
    print("| ride | " + " | ".join(f"{h}: without, with loops (ratio)" for h in head) + " |")
    ratios = {h: [] for h in head}
    for out in args.outs:
        for path in sorted((out / "odometry").iterdir()):
            if path.name.rsplit("-", 1)[0] not in ("block", "eight", "back"):
                continue
            steps, loops, gt, times, _, heights = load(out, path.name)
            runs = {
                "plain": (chain_poses(steps), close_loops(steps, loops)[0]),
            }
            steady = steady_height_steps(steps, heights)[0]
            runs["steady"] = (chain_poses(steady), close_loops(steady, loops)[0])
            for s in args.sigmas:
                cfg = GraphSettings(height=s)
                runs[f"factor {s}"] = (
                    close_loops(steps, [], cfg, heights=heights)[0],
                    close_loops(steps, loops, cfg, heights=heights)[0],
                )
            base = ape(gt, times, runs["plain"][0])
            cells = []
            for h, (without, with_) in runs.items():
                a, b = ape(gt, times, without), ape(gt, times, with_)
                ratios[h].append((path.name, b / base))
                cells.append(f"{a:.3f}, {b:.3f} ({b / base:.2f}x)")
            print(f"| {out.name}/{path.name} | " + " | ".join(cells) + " |", flush=True)
    for h, r in ratios.items():
        closed = [v for n, v in r if not n.startswith("back")]
        print(
            f"{h}: closed rides at most 0.5x of the plain refinement: {sum(v <= 0.5 for v in closed)} of "
            f"{len(closed)}; geometric mean of all ratios {np.exp(np.mean(np.log([v for _, v in r]))):.3f}"
        )


if __name__ == "__main__":
    main()
