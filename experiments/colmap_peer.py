"""The peer a user with 360-degree video would otherwise run: COLMAP's structure from motion on the
benchmark's held-out test rides, as panoramas (a rig of virtual pinhole views per frame), against
``cylsfm odometry`` and ``cylsfm odometry --refine --no-bundle`` on the same rides: the commands and figures behind
RESULTS.md's COLMAP table.

Usage::

    python experiments/colmap_peer.py CHECKPOINT OUT [--rides seq_001 ...] [--frames N]

For each ride:

1. The ride is rendered again as equirectangular frames (``cylsfm synth --projection equirect``, the same
   seed and sequence index as the benchmark, so the same town and the same poses, checked), at
   ``--equirect-width`` (default 1024x512: four times the columns cylsfm's 256x64 cylinder gets).
2. Each frame becomes ``--views`` pinhole views (default 6, turned evenly, ``--fov`` 90 degrees,
   ``--view-size`` 320 pixels square, rendered by :func:`cylsfm.export.colmap.render_view`), one folder a
   view direction: COLMAP's panorama set-up. The views of a frame are declared a rig with the known
   rotations between them (``pycolmap.apply_rig_config``), so that COLMAP solves one pose a frame; the
   cameras are fixed PINHOLE cameras (focal length known, not refined).
3. COLMAP on the CPU: SIFT features (``extract_features``), sequential matching (``match_sequential``,
   ``--overlap`` frames, the rig's views expanded, no loop detection: the rides do not come back), then
   ``incremental_mapping``. Wall time is counted from extraction to the end of the mapping (rendering the
   views not counted).
4. The largest model's frame poses (the rig's frame is view 0, the panorama's own axes) against the ground
   truth: Sim(3)-aligned APE and RPE (``cylsfm.evaluate.pose_metrics.trajectory_metrics``, over the
   registered frames) and the fraction of the ride's frames registered; the number of models.

cylsfm runs ``cylsfm.odometry`` on the benchmark's cylindrical ride (``experiments/out/data``) with
``CHECKPOINT``, without and with ``refine``; its measures come from the same function, over every frame,
with the constant-velocity and zero-motion references beside them. The table is printed and saved as
``OUT/table.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

import cylsfm
from cylsfm.data import read_split
from cylsfm.data.io import load_image, read_tum, save_png
from cylsfm.data.synth import generate_dataset
from cylsfm.evaluate.motion import TURN_DEG, rotation_error_deg, yaw_angle
from cylsfm.evaluate.pose_metrics import trajectory_metrics
from cylsfm.export.colmap import render_view, view_rotations
from cylsfm.geometry import EquirectangularCamera, PinholeCamera
from cylsfm.odometry import OdometrySettings

DATA = Path("experiments/out/data")
SEED = 0  # experiments/run.sh's benchmark
MEASURES = ("ape_rmse", "rpe_trans_rmse", "rpe_rot_deg_rmse")


def test_rides() -> list[str]:
    return sorted({seq for seq, _ in read_split(DATA / "splits" / "default" / "test.txt", DATA)})


def equirect_ride(name: str, out: Path, width: int) -> Path:
    """The benchmark ride ``name`` rendered as equirectangular frames (its poses checked against it)."""
    index = int(name.split("_")[1])
    root = out / "equirect"
    seq = root / name
    frames = len(list((DATA / name / "images").glob("*.png")))  # (a ride's path depends on its length)
    if not (seq / "poses.txt").is_file():
        generate_dataset(
            root, sequences=1, first_index=index, frames=frames, width=width, height=width // 2,
            seed=SEED, projection="equirect", progress=False, overwrite=True,
        )  # fmt: skip
    _, ours = read_tum(seq / "poses.txt")
    _, bench = read_tum(DATA / name / "poses.txt")
    if not np.allclose(ours, bench, atol=1e-9):
        raise SystemExit(f"{seq}: the equirectangular ride does not follow the benchmark's poses")
    return seq


def render_views(seq: Path, images: Path, n: int, args: argparse.Namespace) -> PinholeCamera:
    """The first ``n`` frames' pinhole views as ``images/viewK/FRAME.png``."""
    views = args.views
    view = PinholeCamera.from_fov(args.view_size, args.view_size, args.fov)
    rotations = view_rotations(views)
    frames = sorted((seq / "images").glob("*.png"))[:n]
    if all((images / f"view{k}" / frames[-1].name).is_file() for k in range(views)):
        return view
    for file in frames:
        rgb = load_image(file)
        camera = EquirectangularCamera.full(rgb.shape[1], rgb.shape[0])
        for k, rot in enumerate(rotations):
            save_png(images / f"view{k}" / file.name, render_view(rgb, camera, view, rot))
    return view


def run_colmap(seq: Path, work: Path, n: int, args: argparse.Namespace) -> dict:
    """COLMAP on the views of the ride's first ``n`` frames; its measures against the ground truth."""
    import pycolmap

    images = work / "images"
    view = render_views(seq, images, n, args)
    database = work / "database.db"
    database.unlink(missing_ok=True)
    shutil.rmtree(work / "sparse", ignore_errors=True)
    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"  # COLMAP's pixel centres at +0.5: a centred principal point is W/2
    reader.camera_params = f"{float(view.fx)},{float(view.fy)},{view.width / 2},{view.height / 2}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    pycolmap.extract_features(
        database, images, camera_mode=pycolmap.CameraMode.PER_FOLDER, reader_options=reader,
        extraction_options=extraction, device=pycolmap.Device.cpu,
    )  # fmt: skip
    rig = pycolmap.RigConfig(
        cameras=[
            pycolmap.RigConfigCamera(
                image_prefix=f"view{k}/",
                ref_sensor=k == 0,
                cam_from_rig=None if k == 0 else pycolmap.Rigid3d(np.hstack([rot.T, np.zeros((3, 1))])),
            )
            for k, rot in enumerate(view_rotations(args.views))
        ]
    )
    with pycolmap.Database.open(database) as db:
        pycolmap.apply_rig_config([rig], db)
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = args.overlap
    pairing.expand_rig_images = True
    pairing.loop_detection = False
    pycolmap.match_sequential(
        database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu
    )
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.ba_refine_focal_length = False
    mapping.ba_refine_principal_point = False
    mapping.ba_refine_extra_params = False
    mapping.ba_refine_sensor_from_rig = False
    (work / "sparse").mkdir(parents=True)
    models = pycolmap.incremental_mapping(database, images, work / "sparse", mapping)
    seconds = time.perf_counter() - start
    return {**_colmap_measures(seq, models, n), "seconds": seconds, "frames": n}


def frame_poses(rec) -> tuple[np.ndarray, np.ndarray]:
    """The posed frames of a COLMAP model in frame order: their numbers (the images' file stems) ``[n]``
    and camera-to-world poses ``[n,4,4]`` (the rig's frame: its first view's, the panorama's axes)."""
    index, c2w = [], []
    for frame in rec.frames.values():
        if not frame.has_pose:
            continue
        names = [rec.images[d.id].name for d in frame.data_ids if d.sensor_id.type.name == "CAMERA"]
        index.append(int(Path(names[0]).stem))
        world = np.eye(4)
        world[:3] = frame.rig_from_world.inverse().matrix()
        c2w.append(world)
    order = np.argsort(index)
    return np.asarray(index)[order], np.stack(c2w)[order]


def _colmap_measures(seq: Path, models: dict, n: int) -> dict:
    gt_t, gt = read_tum(seq / "poses.txt")
    gt_t, gt = gt_t[:n], gt[:n]
    if not models:
        return {"registered": 0.0, "models": 0, **dict.fromkeys(MEASURES)}
    index, c2w = frame_poses(max(models.values(), key=lambda r: r.num_reg_frames()))
    stats, aligned = trajectory_metrics(gt, gt_t, c2w, gt_t[index])
    # gross failures: frames placed more than 10x the median error away (and at least 1 m)
    err = np.linalg.norm(aligned - gt[index][:, :3, 3], axis=1)
    wrong = err > max(10 * float(np.median(err)), 1.0)
    rest, _ = trajectory_metrics(gt, gt_t, c2w[~wrong], gt_t[index][~wrong])
    where = _trajectory_where(seq, index, c2w)
    return {
        **where,
        "registered": len(index) / n,
        "models": len(models),
        **{m: stats[m] for m in MEASURES},
        "misplaced": [int(i) for i in index[wrong]],
        "ape_rmse_without_misplaced": rest["ape_rmse"],
        "rpe_trans_rmse_without_misplaced": rest["rpe_trans_rmse"],
    }


def step_errors(gt: np.ndarray, est: np.ndarray, scale: float) -> dict:
    """Where the errors are: the mean error of one frame's step on turning steps (true yaw over
    ``TURN_DEG`` degrees) and on straight ones: translation (metres, the estimate times its Sim(3)
    ``scale``) and rotation (degrees). ``gt``, ``est``: camera-to-world ``[N,4,4]`` of the same frames."""
    true = np.linalg.inv(gt[:-1]) @ gt[1:]
    pred = np.linalg.inv(est[:-1]) @ est[1:]
    turning = np.abs(yaw_angle(true)) > np.radians(TURN_DEG)
    trans = np.linalg.norm(scale * pred[:, :3, 3] - true[:, :3, 3], axis=1)
    rot = rotation_error_deg(pred, true)
    out = {"turning_steps": int(turning.sum()), "straight_steps": int((~turning).sum())}
    for name, sel in (("turning", turning), ("straight", ~turning)):
        out[f"step_trans_{name}"] = float(trans[sel].mean()) if sel.any() else None
        out[f"step_rot_deg_{name}"] = float(rot[sel].mean()) if sel.any() else None
    return out


def _trajectory_where(seq: Path, index: np.ndarray, c2w: np.ndarray) -> dict:
    """:func:`step_errors` over the consecutive frames of ``index`` (frame numbers) of ride ``seq``."""
    gt_t, gt = read_tum(seq / "poses.txt")
    stats, _ = trajectory_metrics(gt, gt_t, c2w, gt_t[index])
    pairs = np.flatnonzero(np.diff(index) == 1)
    keep = np.unique(np.concatenate([pairs, pairs + 1]))
    return step_errors(gt[index[keep]], c2w[keep], stats["scale"]) if len(keep) > 1 else {}


def remeasure(out: Path) -> dict:
    """The table again from the COLMAP models already in ``OUT`` (their wall times kept)."""
    import pycolmap

    table = json.loads((out / "table.json").read_text())
    for name, rows in table.items():
        seq = out / "equirect" / name
        models = {
            int(d.name): pycolmap.Reconstruction(d)
            for d in sorted((out / "colmap" / name / "sparse").iterdir())
            if d.is_dir()
        }
        n = round(rows["COLMAP (panorama rig)"].get("frames") or len(list((seq / "images").glob("*.png"))))
        rows["COLMAP (panorama rig)"].update(_colmap_measures(seq, models, n))
        for method, file in (
            ("cylsfm odometry", out / "network" / name / "trajectory.txt"),
            ("cylsfm odometry --refine --no-bundle", out / "refine" / name / "trajectory.txt"),
        ):
            if method in rows and file.is_file():
                _, c2w = read_tum(file)
                rows[method].update(_trajectory_where(DATA / name, np.arange(len(c2w)), c2w))
    return table


def run_cylsfm(name: str, checkpoint: str, out: Path, refine: bool) -> dict:
    result = cylsfm.odometry(
        DATA / name, checkpoint, out, OdometrySettings(progress=False, refine=refine, bundle=False)
    )
    assert result.metrics is not None
    ours = next(iter(result.metrics.values()))
    return {
        "registered": 1.0,
        **{m: ours[m] for m in MEASURES},
        "seconds": result.seconds,
        "constant_velocity": result.metrics["constant_velocity"]["ape_rmse"],
        "zero_motion": result.metrics["zero_motion"]["ape_rmse"],
    }


def show(table: dict) -> None:
    print(
        "| ride | method | APE rmse (m) | RPE trans (m) | RPE rot (deg) | registered | models | misplaced "
        "frames: APE, RPE without them | wall (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for ride, rows in table.items():
        for method, r in rows.items():
            cells = ["-" if r.get(m) is None else f"{r[m]:.3f}" for m in MEASURES]
            models = r.get("models", "")
            wrong = ""
            if r.get("misplaced"):
                wrong = (
                    f"{len(r['misplaced'])} ({', '.join(map(str, r['misplaced']))}): "
                    f"{r['ape_rmse_without_misplaced']:.3f}, {r['rpe_trans_rmse_without_misplaced']:.3f}"
                )
            elif "misplaced" in r:
                wrong = "0"
            print(
                f"| {ride} | {method} | {' | '.join(cells)} | {r['registered']:.0%} | {models} | {wrong} | "
                f"{r['seconds']:.0f} |"
            )
        ref = rows.get("cylsfm odometry", {})
        if "constant_velocity" in ref:
            print(
                f"| {ride} | constant velocity / zero motion (APE) | {ref['constant_velocity']:.3f} / "
                f"{ref['zero_motion']:.3f} | | | | | | |"
            )


def show_where(table: dict) -> None:
    print(
        "\n| ride | method | turning steps | step error on turns (m / deg) | "
        "straight steps | step error on straight (m / deg) |"
    )
    print("|---|---|---|---|---|---|")
    for ride, rows in table.items():
        for method, r in rows.items():
            if "turning_steps" not in r:
                continue
            cells = []
            for part in ("turning", "straight"):
                t, a = r[f"step_trans_{part}"], r[f"step_rot_deg_{part}"]
                cells += [str(r[f"{part}_steps"]), "-" if t is None else f"{t:.4f} / {a:.3f}"]
            print(f"| {ride} | {method} | {' | '.join(cells)} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("out", type=Path)
    p.add_argument("--rides", nargs="*", help="benchmark rides (default: the test split's)")
    p.add_argument("--frames", type=int, help="the first N frames of each ride (default: all)")
    p.add_argument("--equirect-width", type=int, default=1024)
    p.add_argument("--views", type=int, default=6)
    p.add_argument("--fov", type=float, default=90.0)
    p.add_argument("--view-size", type=int, default=320)
    p.add_argument("--overlap", type=int, default=5, help="sequential matching: frames each side")
    p.add_argument("--skip-cylsfm", action="store_true")
    p.add_argument("--remeasure", action="store_true", help="only measure the COLMAP models in OUT again")
    args = p.parse_args()
    if args.remeasure:
        table = remeasure(args.out)
        (args.out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
        show(table)
        show_where(table)
        return
    table: dict = {}
    for name in args.rides or test_rides():
        seq = equirect_ride(name, args.out, args.equirect_width)
        n = args.frames or len(list((seq / "images").glob("*.png")))
        rows = {"COLMAP (panorama rig)": run_colmap(seq, args.out / "colmap" / name, n, args)}
        print(name, "COLMAP", rows["COLMAP (panorama rig)"], flush=True)
        if not args.skip_cylsfm:
            for label, refine in (("cylsfm odometry", False), ("cylsfm odometry --refine --no-bundle", True)):
                folder = args.out / ("refine" if refine else "network") / name
                shutil.rmtree(folder, ignore_errors=True)  # timed from scratch, not resumed
                rows[label] = run_cylsfm(name, args.checkpoint, folder, refine)
                print(name, label, rows[label], flush=True)
        table[name] = rows
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
    show(table)


if __name__ == "__main__":
    main()
