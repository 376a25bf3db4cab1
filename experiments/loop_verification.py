"""How well the loop verification tells a place passed before from one that only looks like it: the
measurement behind the threshold of :attr:`cylsfm.odometry.LoopSettings.min_inliers`.

Usage::

    python experiments/loop_verification.py CHECKPOINT OUT [--towns 0 2 3] [--routes back stairs block eight]

Each ride (``experiments/loops.py``'s rides, generated under ``OUT/data``) runs through ``cylsfm odometry
--refine --loops`` with the odometry's gates on (drift and heading) but no inlier threshold and no support:
every candidate pair is aligned both ways and its inlier fraction kept. A pair's relative pose is right
when it is within 5 degrees and 2 m plus a tenth of the distance of the truth (``loops.judge``), wrong
otherwise.
Printed per ride and over all, for the pairs that passed the gates: the inlier fractions of the right and
of the wrong pairs (quantiles), and how many of each a threshold accepts. The default towns
are training towns: the threshold is chosen here and measured on the held-out towns by
``experiments/loops.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from loops import each_ride, judge, ride_arguments

import cylsfm
from cylsfm.data.io import read_tum
from cylsfm.odometry import OdometrySettings
from cylsfm.odometry.loops import LoopSettings

THRESHOLDS = (0.4, 0.5, 0.6, 0.7, 0.8)


def pairs_of(seq: Path, out: Path, checkpoint: str) -> list[dict]:
    """Every pair that passed the odometry's gates, with its inlier fraction, its true distance (metres),
    its rotation and translation errors (degrees, metres) and whether it is right."""
    loop = LoopSettings(min_inliers=0.0, support=1)
    settings = OdometrySettings(progress=False, refine=True, loops=True, loop=loop, bundle=False)
    result = cylsfm.odometry(seq, checkpoint, out, settings)
    _, gt = read_tum(seq / "poses.txt")
    kept = []
    for p in (result.loops or {"pairs": []})["pairs"]:
        if p["reason"] not in ("beyond_drift", "turned_beyond_drift"):
            kept.append({**p, **judge(p, gt, out)})
    return kept


def summary(pairs: list[dict]) -> str:
    true = np.array([p["inliers"] for p in pairs if p["right"]])
    false = np.array([p["inliers"] for p in pairs if not p["right"]])

    def q(x: np.ndarray) -> str:
        return "-" if len(x) == 0 else " / ".join(f"{v:.2f}" for v in np.quantile(x, [0.1, 0.5, 0.9, 1.0]))

    counts = ", ".join(
        f">={t}: {int((true >= t).sum())} right, {int((false >= t).sum())} wrong" for t in THRESHOLDS
    )
    return f"right {len(true)} (10/50/90/100%: {q(true)}); wrong {len(false)} ({q(false)}); {counts}"


def main() -> None:
    args = ride_arguments(__doc__.split("\n\n")[0], [0, 2, 3], ["back", "stairs", "block", "eight"])
    everything = []
    for name, seq, out in each_ride(args):
        pairs = pairs_of(seq, out, args.checkpoint)
        everything += pairs
        print(name, summary(pairs), flush=True)
    print("all", summary(everything))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "pairs.json").write_text(json.dumps(everything, indent=1) + "\n")


if __name__ == "__main__":
    main()
