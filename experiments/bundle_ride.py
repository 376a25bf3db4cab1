"""The bundle adjustment on a real ride, before it is a stage of ``cylsfm odometry``: the odometry's
trajectory, then SIFT features on every frame at its own resolution, matches guided by the odometry
between each frame and the next few, tracks, and :func:`cylsfm.odometry.bundle.bundle_adjust`; scored
against the ride's ground truth beside the odometry it started from.

Usage::

    python experiments/bundle_ride.py SEQUENCE CHECKPOINT OUT [--refine] [--span 4]

``SEQUENCE``: a dataset sequence with ``poses.txt``. Printed: the odometry's and the adjusted ride's APE
(Sim(3), m), per-step translation (m, in the truth's scale) and rotation (degrees) errors, the features,
matches, tracks and observations kept, and the seconds each part took.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

import cylsfm
from cylsfm.data.format import load_image, scan_dataset
from cylsfm.evaluate.pose_metrics import trajectory_metrics
from cylsfm.geometry import invert
from cylsfm.geometry.bearings import pixel_bearings
from cylsfm.odometry import OdometrySettings
from cylsfm.odometry.bundle import BundleSettings, bundle_adjust
from cylsfm.odometry.bundle.features import detect
from cylsfm.odometry.bundle.matching import match_pair, tracks_of


def step_errors(c2w: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Mean per-step translation error (m, the estimate in the truth's scale by the ride's length) and
    rotation error (degrees)."""

    def length(c):
        return np.linalg.norm(np.diff(c[:, :3, 3], axis=0), axis=1).sum()

    scale = length(truth) / length(c2w)
    trans, rot = [], []
    for j in range(len(truth) - 1):
        a, b = invert(c2w[j]) @ c2w[j + 1], invert(truth[j]) @ truth[j + 1]
        trans.append(np.linalg.norm(a[:3, 3] * scale - b[:3, 3]))
        rot.append(math.degrees(math.acos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1))))
    return float(np.mean(trans)), float(np.mean(rot))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("sequence", type=Path)
    parser.add_argument("checkpoint")
    parser.add_argument("out", type=Path)
    parser.add_argument("--refine", action="store_true")
    parser.add_argument("--span", type=int, default=4, help="each frame matched with the next N")
    args = parser.parse_args()
    seq = scan_dataset(args.sequence)[0]
    t0 = time.perf_counter()
    odo = cylsfm.odometry(
        seq.path,
        args.checkpoint,
        args.out,
        OdometrySettings(refine=args.refine, progress=False, loops=False, bundle=False),
    )
    t1 = time.perf_counter()
    cam = seq.camera
    feats, bearings = [], []
    for path in seq.images:
        f = detect(load_image(path), cam.wraps, None)
        feats.append(f)
        bearings.append(pixel_bearings(cam, torch.from_numpy(f.uv)).numpy() if len(f) else np.zeros((0, 3)))
    t2 = time.perf_counter()
    matches = {}
    m = len(feats)
    for i in range(m):
        for j in range(i + 1, min(m, i + 1 + args.span)):
            rel = invert(odo.c2w[j]) @ odo.c2w[i]  # T_{i->j}: p_j = T p_i
            matches[(i, j)] = match_pair(feats[i], feats[j], bearings[i], bearings[j], rel)
    obs = tracks_of(matches, bearings)
    t3 = time.perf_counter()
    done = bundle_adjust(odo.c2w, obs, 1 / float(cam.fx), BundleSettings())
    t4 = time.perf_counter()
    truth = seq.poses
    times = np.asarray(seq.timestamps)
    for name, c2w in (("odometry", odo.c2w), ("adjusted", done.c2w)):
        ape = trajectory_metrics(truth, times, c2w, times)[0]["ape_rmse"]
        trans, rot = step_errors(c2w, truth)
        print(f"{name:9s} APE {ape:.3f} m   step {trans * 1000:.1f} mm {rot:.3f} deg")
    print(
        f"features {np.mean([len(f) for f in feats]):.0f} a frame; matches {sum(len(v) for v in matches.values())}; "
        f"tracks {obs.points}, observations {len(obs.frame)}, kept {int(done.inliers.sum())}; rounds {done.rounds}"
    )
    print(
        f"seconds: odometry {t1 - t0:.1f}, features {t2 - t1:.1f}, matching {t3 - t2:.1f}, adjustment {t4 - t3:.1f}"
    )


if __name__ == "__main__":
    main()
