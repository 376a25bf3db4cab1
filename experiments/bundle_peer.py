"""COLMAP against cylsfm's bundle adjustment at the pixels cylsfm reads: the benchmark's test rides rendered
as cylinder panoramas (``cylsfm synth``, seed 0, the same town and poses as the benchmark ride of that
index), each frame also resampled into the band of an equirectangular image of the same angular
resolution (rows the cylinder does not see are black), which COLMAP reads with its native
EQUIRECTANGULAR camera (``pycolmap.panorama.run_spherical``: SIFT, sequential matching, incremental
mapping, 2 threads, on the CPU).

Usage::

    python experiments/bundle_peer.py CHECKPOINT OUT [--rides 1 8 15] [--frames 150] [--width 512]
    python experiments/bundle_peer.py CHECKPOINT OUT --equirect [--width 1024]

``--drift`` only adds each saved result's drift over windows of frames (:func:`drift`) to the table.
``--keep-colmap`` reruns cylsfm only, keeping the COLMAP rows that ``OUT/table.json`` already has (a ride
without one runs COLMAP too).

With ``--equirect`` the rides are rendered as equirectangular frames of ``--width`` x ``--width``/2
instead, which cylsfm reads as they are (its features at their resolution) and COLMAP as its rig of six
pinhole views of 90 degrees, 320 pixels square, sequential matching with 5 frames each side
(``experiments/colmap_peer.py``'s set-up, its best at 1024x512).

Per ride, one run each, one after the other (so that they share the machine alike), each from nothing:

1. ``cylsfm odometry --refine --no-bundle`` (loops off: the rides do not come back);
2. ``cylsfm odometry --refine --bundle``;
3. COLMAP.

Each is scored against the ride's poses: Sim(3) APE and RPE over the registered frames, the registered
fraction, the models, the frames more than 1 m off after the alignment (and the APE without them), the
mean error of a step on turns and on straight road (translation in metres, rotation in degrees), and the
wall time from frames to poses (COLMAP: from feature extraction to the end of mapping; cylsfm: the whole
run, the model's loading included). Printed as a table and saved as ``OUT/table.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))

from colmap_peer import _colmap_measures, _trajectory_where, frame_poses

import cylsfm
from cylsfm.data.io import load_image, read_tum, save_png
from cylsfm.data.synth import generate_dataset
from cylsfm.evaluate.pose_metrics import trajectory_metrics
from cylsfm.geometry import CylindricalCamera, EquirectangularCamera, sample_image
from cylsfm.odometry import OdometrySettings

SEED = 0  # the benchmark's


def rendered_ride(out: Path, index: int, frames: int, width: int, equirect: bool) -> Path:
    root = out / ("equirect_frames" if equirect else "cylinder")
    seq = root / f"seq_{index:03d}"
    if not (seq / "poses.txt").is_file():
        generate_dataset(
            root, sequences=1, first_index=index, frames=frames, width=width,
            height=width // 2 if equirect else width // 4, seed=SEED, progress=False, overwrite=True,
            workers=1, projection="equirect" if equirect else "cylindrical",
        )  # fmt: skip
    return seq


def run_colmap_rig(seq: Path, work: Path, frames: int) -> dict:
    from colmap_peer import run_colmap as rig

    views = argparse.Namespace(views=6, fov=90.0, view_size=320, overlap=5)
    (work / "images").mkdir(parents=True, exist_ok=True)
    shutil.rmtree(work / "sparse", ignore_errors=True)
    row = rig(seq, work, frames, views)
    if row.get("ape_rmse") is not None:
        row.update(_steps_without(seq, _models(work / "sparse"), row["misplaced"]))
    return row


def _models(sparse: Path) -> dict:
    import pycolmap

    return {int(d.name): pycolmap.Reconstruction(d) for d in sparse.iterdir() if d.is_dir()}


def equirect_frames(seq: Path, out: Path) -> Path:
    """Each cylinder frame of ``seq`` resampled into an equirectangular image of the same width (its rows
    beyond the cylinder's band black): ``out/NNNNNN.png``, named by the frame's index."""
    images = sorted((seq / "images").glob("*.png"))
    if out.is_dir() and len(list(out.glob("*.png"))) == len(images):
        return out
    out.mkdir(parents=True, exist_ok=True)
    first = load_image(images[0])
    h, w = first.shape[:2]
    cyl = CylindricalCamera.full(w, h)
    eq = EquirectangularCamera.full(w, w // 2)
    rays = eq.rays(eq.pixel_grid(1, dtype=torch.float64))
    uv = cyl.project(rays)
    for i, path in enumerate(images):
        img = torch.from_numpy(load_image(path)).permute(2, 0, 1)[None].double()
        warped, inside = sample_image(img, uv, True)
        pano = (warped * inside).round().clamp(0, 255).byte()[0].permute(1, 2, 0).numpy()
        save_png(out / f"{i:06d}.png", pano)
    return out


def run_colmap(seq: Path, images: Path, work: Path, frames: int) -> dict:
    import pycolmap
    from pycolmap.panorama import PanoramaReconstructionOptions, run_spherical

    shutil.rmtree(work, ignore_errors=True)
    (work / "sparse").mkdir(parents=True)
    start = time.perf_counter()
    options = PanoramaReconstructionOptions(num_threads=2, use_gpu=False, show_progress=False)
    pycolmap.set_random_seed(0)
    models = run_spherical(images, options, work / "database.db", work / "sparse")
    seconds = time.perf_counter() - start
    largest = max((m.num_reg_frames() for m in models.values()), default=0)
    if largest < 3:  # nothing to align
        none = dict.fromkeys(("ape_rmse", "rpe_trans_rmse", "rpe_rot_deg_rmse"))
        return {
            **none,
            "registered": largest / frames,
            "models": len(models),
            "misplaced": [],
            "seconds": seconds,
        }
    measures = _colmap_measures(seq, models, frames)
    return {**measures, **_steps_without(seq, models, measures["misplaced"]), "seconds": seconds}


def _steps_without(seq: Path, models: dict, misplaced: list[int]) -> dict:
    """The step errors of COLMAP's largest model without its misplaced frames (and their steps)."""
    index, c2w = frame_poses(max(models.values(), key=lambda r: r.num_reg_frames()))
    keep = ~np.isin(index, misplaced)
    where = _trajectory_where(seq, index[keep], c2w[keep])
    return {f"{k}_without_misplaced": v for k, v in where.items() if k.startswith("step_")}


def remeasure(out: Path) -> None:
    """Add the steps without the misplaced frames to ``OUT/table.json`` from the COLMAP models there."""
    table_file = out / "table.json"
    table = json.loads(table_file.read_text())
    for name, rows in table.items():
        row = rows["COLMAP (EQUIRECTANGULAR)"]
        if row.get("ape_rmse") is None:
            continue
        models = _models(out / "colmap" / name / "sparse")
        row.update(_steps_without(out / "cylinder" / name, models, row["misplaced"]))
    table_file.write_text(json.dumps(table, indent=1))


def run_cylsfm(seq: Path, checkpoint: str, out: Path, bundle: bool) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    start = time.perf_counter()
    result = cylsfm.odometry(
        seq, checkpoint, out, OdometrySettings(refine=True, bundle=bundle, loops=False, progress=False)
    )
    seconds = time.perf_counter() - start
    gt_t, gt = read_tum(seq / "poses.txt")
    index = np.arange(len(result.c2w))
    stats, aligned = trajectory_metrics(gt, gt_t, result.c2w, gt_t)
    off = np.linalg.norm(aligned - gt[:, :3, 3], axis=1)
    return {
        **_trajectory_where(seq, index, result.c2w),
        "registered": 1.0,
        "models": 1,
        "ape_rmse": stats["ape_rmse"],
        "rpe_trans_rmse": stats["rpe_trans_rmse"],
        "rpe_rot_deg_rmse": stats["rpe_rot_deg_rmse"],
        "misplaced": [int(i) for i in np.flatnonzero(off > 1.0)],
        "seconds": seconds,
        "constant_velocity": result.metrics["constant_velocity"]["ape_rmse"],
        "stages": result.timings,
    }


def drift(truth: np.ndarray, c2w: np.ndarray, apart: int = 60, stretch: int = 30) -> dict:
    """How a ride ``c2w [n,4,4]`` drifts from the ``truth [n,4,4]`` (the same frames): the RMS error of the
    relative pose's rotation and of its direction of travel (degrees) over frames ``apart``, and the
    standard deviation of each ``stretch``-frame stretch's length over the truth's, divided by their
    median (the scale's drift)."""
    from cylsfm.geometry import invert

    def relative(poses: np.ndarray, i: int, gap: int) -> np.ndarray:
        return invert(poses[i]) @ poses[i + gap]

    rot, direction = [], []
    for i in range(len(c2w) - apart):
        true, est = relative(truth, i, apart), relative(c2w, i, apart)
        off = (invert(true) @ est)[:3, :3]
        rot.append(np.degrees(np.arccos(np.clip((np.trace(off) - 1) / 2, -1, 1))))
        cos = true[:3, 3] @ est[:3, 3] / max(np.linalg.norm(true[:3, 3]) * np.linalg.norm(est[:3, 3]), 1e-12)
        direction.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    scale = [
        np.linalg.norm(relative(c2w, i, stretch)[:3, 3])
        / max(np.linalg.norm(relative(truth, i, stretch)[:3, 3]), 1e-9)
        for i in range(len(c2w) - stretch)
    ]
    scale = np.asarray(scale) / np.median(scale)
    return {
        f"drift_rot_deg_{apart}": float(np.sqrt(np.mean(np.square(rot)))),
        f"drift_direction_deg_{apart}": float(np.sqrt(np.mean(np.square(direction)))),
        f"scale_spread_{stretch}": float(np.std(scale)),
    }


def add_drift(out: Path, equirect: bool) -> None:
    """Add :func:`drift` of every saved result (cylsfm's trajectories, COLMAP's largest model) to
    ``OUT/table.json``, over the frames each placed."""
    table_file = out / "table.json"
    table = json.loads(table_file.read_text())
    for name, rows in table.items():
        seq = out / ("equirect_frames" if equirect else "cylinder") / name
        _, truth = read_tum(seq / "poses.txt")
        for method, row in rows.items():
            if method.startswith("COLMAP"):
                sparse = out / "colmap" / name / "sparse"
                if not sparse.is_dir() or not any(sparse.iterdir()):
                    continue
                index, c2w = frame_poses(max(_models(sparse).values(), key=lambda r: r.num_reg_frames()))
            else:
                kind = "bundle" if "--bundle" in method else "refine"
                _, c2w = read_tum(out / kind / name / "trajectory.txt")
                index = np.arange(len(c2w))
            row.update(drift(truth[index], c2w))
            print(name, method, {k: round(v, 4) for k, v in row.items() if k.startswith(("drift", "scale"))})
    table_file.write_text(json.dumps(table, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("out", type=Path)
    parser.add_argument("--rides", type=int, nargs="+", default=[1, 8, 15])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--equirect", action="store_true", help="equirectangular frames; COLMAP's rig")
    parser.add_argument(
        "--remeasure", action="store_true", help="only add COLMAP's steps without misplaced frames"
    )
    parser.add_argument("--drift", action="store_true", help="only add the drift of each saved result")
    parser.add_argument(
        "--keep-colmap", action="store_true", help="run cylsfm only; keep COLMAP's rows already in the table"
    )
    args = parser.parse_args()
    if args.remeasure:
        remeasure(args.out)
        return
    if args.drift:
        add_drift(args.out, args.equirect)
        return
    table_file = args.out / "table.json"
    table = json.loads(table_file.read_text()) if table_file.is_file() else {}
    for index in args.rides:
        name = f"seq_{index:03d}"
        seq = rendered_ride(args.out, index, args.frames, args.width, args.equirect)
        rows = table.setdefault(name, {})
        rows["cylsfm --refine --no-bundle"] = run_cylsfm(
            seq, args.checkpoint, args.out / "refine" / name, False
        )
        rows["cylsfm --refine --bundle"] = run_cylsfm(seq, args.checkpoint, args.out / "bundle" / name, True)
        if args.keep_colmap and any(k.startswith("COLMAP") for k in rows):
            pass
        elif args.equirect:
            rows["COLMAP (rig of views)"] = run_colmap_rig(seq, args.out / "colmap" / name, args.frames)
        else:
            images = equirect_frames(seq, args.out / "equirect" / name)
            rows["COLMAP (EQUIRECTANGULAR)"] = run_colmap(
                seq, images, args.out / "colmap" / name, args.frames
            )
        table_file.write_text(json.dumps(table, indent=1))
        for method, r in rows.items():
            print(
                f"{name} {method:26s} APE {r['ape_rmse']} RPE {r['rpe_trans_rmse']} / "
                f"{r['rpe_rot_deg_rmse']} reg {r['registered']:.2f} models {r['models']} "
                f"off>1m {len(r['misplaced'])} steps turn {r.get('step_trans_turning')} / "
                f"{r.get('step_rot_deg_turning')} straight {r.get('step_trans_straight')} / "
                f"{r.get('step_rot_deg_straight')} wall {r['seconds']:.1f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
