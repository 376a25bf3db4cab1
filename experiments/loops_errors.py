"""What is left after the loops: the refined odometry's errors taken apart, and the pose graph solved again
under other uncertainties, from the states that ``experiments/loops.py`` left behind.

Usage::

    python experiments/loops_errors.py OUT [OUT ...] [--grid]

``OUT``: an output folder of ``experiments/loops.py`` (its ``data/`` and ``odometry/`` rides). For each
closed or out-and-back ride, the APE (Sim(3), m) of the refined odometry and of its loops closed by
:func:`cylsfm.odometry.loops.graph.close_loops`, and the same for the steps with one part of their error
removed (replaced by the truth's, the truth brought to the odometry's unit by the ratio of median step
lengths): the rotations (``rotation true``), the length of each translation (``length true``), and both
rotation and direction (``only lengths wrong``); then the step lengths corrected by the camera height the
odometry fitted to each frame's depth (``height unit``: the depth's unit, frame by frame). With
``--grid``, the closed APE over the refined APE for each step uncertainty of a small grid (rotation,
translation, scale): the settings of :class:`~cylsfm.odometry.loops.graph.GraphSettings` against others.
Nothing is run again: odometry's saved state holds its steps and verified loops.
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


def load(out: Path, name: str):
    """``(refined steps [M-1,4,4], loops, true c2w [M,4,4], times [M], true steps, heights [M])``."""
    kind, town = name.rsplit("-", 1)
    state = State.load(out / "odometry" / name / STATE_FILE, None)
    if state is None:
        raise SystemExit(
            f"{out / 'odometry' / name}: no saved odometry state (run experiments/loops.py first)"
        )
    steps, heights = np.stack(state.refined), np.asarray(state.heights)
    times, gt = read_tum(out / "data" / kind / f"seq_{town}" / "poses.txt")
    truth = np.linalg.inv(gt[1:]) @ gt[:-1]  # T_{j->j+1}
    return steps, state.loops or [], gt, times, truth, heights


def ape(gt: np.ndarray, times: np.ndarray, c2w: np.ndarray) -> float:
    return float(trajectory_metrics(gt, times, c2w, times)[0]["ape_rmse"])


def variants(steps: np.ndarray, truth: np.ndarray, heights: np.ndarray) -> dict[str, np.ndarray]:
    """The steps with one part of their error removed (see the module docstring)."""
    length = np.linalg.norm(steps[:, :3, 3], axis=1)
    true_length = np.linalg.norm(truth[:, :3, 3], axis=1)
    unit = np.median(true_length) / np.median(length)
    true_dir = truth[:, :3, 3] / np.maximum(true_length, 1e-12)[:, None]
    out = {"refined": steps}
    out["rotation true"] = steps.copy()
    out["rotation true"][:, :3, :3] = truth[:, :3, :3]
    out["length true"] = steps.copy()
    out["length true"][:, :3, 3] *= (true_length / unit / np.maximum(length, 1e-12))[:, None]
    out["only lengths wrong"] = out["rotation true"].copy()
    out["only lengths wrong"][:, :3, 3] = true_dir * length[:, None]
    height = heights / np.median(heights)
    out["height unit"] = steps.copy()
    out["height unit"][:, :3, 3] /= ((height[:-1] + height[1:]) / 2)[:, None]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("outs", type=Path, nargs="+")
    parser.add_argument("--grid", action="store_true")
    args = parser.parse_args()
    rides = []
    for out in args.outs:
        for path in sorted((out / "odometry").iterdir()):
            if path.name.rsplit("-", 1)[0] in ("block", "eight", "back"):
                rides.append((out, path.name, *load(out, path.name)))
    print("| ride | each variant: APE refined -> loops closed (m) |")
    for out, name, steps, loops, gt, times, truth, heights in rides:
        cells = []
        for label, s in variants(steps, truth, heights).items():
            c2w, _ = close_loops(s, loops)
            cells.append(f"{label} {ape(gt, times, chain_poses(s)):.2f} -> {ape(gt, times, c2w):.2f}")
        print(f"| {out.name}/{name} | " + " | ".join(cells) + " |")
    if not args.grid:
        return
    base = [ape(gt, times, chain_poses(steps)) for _, _, steps, _, gt, times, _, _ in rides]
    print("| rotation (deg) | translation | scale | max | mean | " + " | ".join(r[1] for r in rides) + " |")
    for rot, trans, scale in itertools.product((0.1, 0.25, 1.0), (0.05, 0.1, 0.2), (0.002, 0.005, 0.02)):
        cfg = GraphSettings(step_rotation_deg=rot, step_translation=trans, step_scale=scale)
        ratios = np.array(
            [
                ape(gt, times, close_loops(steps, loops, cfg)[0]) / b
                for (_, _, steps, loops, gt, times, _, _), b in zip(rides, base, strict=True)
            ]
        )
        row = " | ".join(f"{r:.2f}" for r in ratios)
        print(f"| {rot} | {trans} | {scale} | {ratios.max():.2f} | {ratios.mean():.2f} | {row} |", flush=True)


if __name__ == "__main__":
    main()
