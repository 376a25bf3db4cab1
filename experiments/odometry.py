"""Whole-ride odometry on the held-out test rides of the demo benchmark: the commands and figures behind
RESULTS.md's odometry tables.

Usage::

    python experiments/odometry.py CHECKPOINT OUT [VARIANT ...]

VARIANT is one of ``refine`` (``cylsfm odometry --refine``), ``refine-fp32`` (``--refine --no-amp``), ``refine-kf5`` (``--keyframes 5``),
``true-depth`` (``--refine --depth-from`` the benchmark: the test of the refinement itself) and
``rolled`` / ``rolled-kf5`` (the rides with every frame rolled by a random yaw, as a camera mounted turned;
ground truth turned with them), ``refine-ahead`` / ``rolled-ahead`` (``--mount-yaw 0``: the pose network
reads the frames as they are, the direction of travel not looked for), ``helmet`` / ``helmet-nomask`` / ``roof`` /
``roof-nomask`` (the rides with a synthetic occluder painted into every frame, ``cylsfm synth --occluder``:
with the sequence's mask.png, and with ``--no-mask``). Default: all. Each run writes ``OUT/VARIANT/SEQ/`` (the files of ``cylsfm
odometry``); the table (per variant: the trajectory, the pose network alone, the visual compass, constant
velocity, zero motion; mean over the rides) is printed and saved as ``OUT/table.json``.

The benchmark data is the one ``experiments/run.sh`` generates (``experiments/out/data``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

import cylsfm
from cylsfm.data import read_split, scan_dataset
from cylsfm.data.format import SequenceWriter, load_depth, load_image
from cylsfm.data.synth.occluder import occluder_mask, occluder_texture
from cylsfm.geometry import roll_columns, roll_pose
from cylsfm.odometry import OdometrySettings

DATA = Path("experiments/out/data")
VARIANTS = {
    "refine": {"refine": True},
    "refine-fp32": {"refine": True, "amp": False},
    "refine-kf5": {"refine": True, "keyframe_every": 5},
    "true-depth": {"refine": True, "depth_from": DATA},
    "rolled": {"refine": True, "rolled": True},
    "rolled-kf5": {"refine": True, "keyframe_every": 5, "rolled": True},
    "refine-ahead": {"refine": True, "mount_yaw": 0.0},
    "rolled-ahead": {"refine": True, "mount_yaw": 0.0, "rolled": True},
    "helmet": {"refine": True, "occluder": "helmet"},
    "helmet-nomask": {"refine": True, "occluder": "helmet", "mask": False},
    "roof": {"refine": True, "occluder": "roof"},
    "roof-nomask": {"refine": True, "occluder": "roof", "mask": False},
}
MEASURES = ("ape_rmse", "rpe_trans_rmse", "rot_err_deg_mean", "rot_err_deg_turning", "dir_err_deg_mean")


def test_rides() -> list[str]:
    return sorted({seq for seq, _ in read_split(DATA / "splits" / "default" / "test.txt", DATA)})


def rolled_copy(name: str, out: Path, seed: int) -> Path:
    """The ride with every frame rolled by one random number of columns (ground truth turned with it)."""
    dest = out / name
    if (dest / "camera.json").is_file():
        return dest
    seq = {s.name: s for s in scan_dataset(DATA)}[name]
    w = seq.camera.width
    k = int(np.random.default_rng(seed).integers(1, w))
    writer = SequenceWriter(dest, seq.camera)
    for i, img in enumerate(seq.images):
        depth = seq.depth_path(i)
        writer.add_frame(
            roll_columns(load_image(img), k, axis=1),
            roll_columns(load_depth(depth), k, axis=1) if depth else None,
        )
    poses = np.stack([roll_pose(p, k, w, camera_to_world=True) for p in seq.poses])
    return writer.finish(poses, timestamps=seq.timestamps)


def occluded_copy(name: str, out: Path, kind: str) -> Path:
    """The ride with the synthetic occluder ``kind`` in every frame (no depth there) and its mask.png."""
    dest = out / name
    if (dest / "camera.json").is_file():
        return dest
    seq = {s.name: s for s in scan_dataset(DATA)}[name]
    occ = occluder_mask(*seq.camera.size, kind)
    texture = occluder_texture(*seq.camera.size)
    writer = SequenceWriter(dest, seq.camera)
    for i, img in enumerate(seq.images):
        depth = seq.depth_path(i)
        writer.add_frame(
            np.where(occ[..., None], texture, load_image(img)),
            np.where(occ, np.float32(0), load_depth(depth)) if depth else None,
        )
    return writer.finish(seq.poses, timestamps=seq.timestamps, mask=~occ)


def run(checkpoint: str, out: Path, variants: list[str]) -> dict:
    table: dict = {}
    for variant in variants:
        opts = dict(VARIANTS[variant])
        rolled = opts.pop("rolled", False)
        occluder = opts.pop("occluder", None)
        per_ride = []
        for n, name in enumerate(test_rides()):
            ride = rolled_copy(name, out / "rolled-data", seed=n) if rolled else DATA / name
            ride = occluded_copy(name, out / f"{occluder}-data", occluder) if occluder else ride
            result = cylsfm.odometry(
                ride,
                checkpoint,
                out / variant / name,
                OdometrySettings(progress=False, **{"bundle": False, **opts}),
            )
            per_ride.append(result.metrics)
            print(
                f"{variant} {name}: {result.seconds:.1f} s, {len(result.c2w) / result.seconds:.2f} frames/s",
                flush=True,
            )
        table[variant] = {
            src: {
                m: float(np.mean([r[src][m] for r in per_ride if r[src].get(m) is not None] or [np.nan]))
                for m in MEASURES
            }
            for src in per_ride[0]
        }
    return table


def show(table: dict) -> None:
    print(f"| variant | trajectory | {' | '.join(MEASURES)} | APE / const. vel. |")
    print("|" + "---|" * (len(MEASURES) + 3))
    for variant, rows in table.items():
        cv = rows["constant_velocity"]["ape_rmse"]
        for src, m in rows.items():
            cells = " | ".join("-" if not np.isfinite(m[k]) else f"{m[k]:.4f}" for k in MEASURES)
            print(f"| {variant} | {src} | {cells} | {m['ape_rmse'] / cv:.3f}x |")


if __name__ == "__main__":
    ckpt, out = sys.argv[1], Path(sys.argv[2])
    chosen = sys.argv[3:] or list(VARIANTS)
    result = run(ckpt, out, chosen)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.json").write_text(json.dumps(result, indent=2) + "\n")
    show(result)
