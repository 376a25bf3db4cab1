"""``cylsfm export colmap`` and ``cylsfm export rerun``: a ride's odometry, its frames and their depth for
the 3D tools users move on to: a COLMAP model and a nerfstudio ``transforms.json`` (for Gaussian splatting
and NeRF trainers, :mod:`cylsfm.export.colmap`), a rerun recording (:mod:`cylsfm.export.rerun`).

An export consumes an odometry run: the one given (``odometry=DIR``, an output of ``cylsfm odometry`` made
with the same input, checkpoint and options, which its fingerprint in ``DIR/odometry.json`` must confirm),
or one that it runs itself through the same pipeline, with every frame's depth. Either way the ride is
opened, planned and the model loaded once (:func:`~cylsfm.odometry.job.resolve_job`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.format import load_depth
from ..data.io import read_tum
from ..errors import CylsfmError
from ..export.colmap import ColmapWriter, ViewOptions
from ..geometry import Camera
from ..geometry.bearings import pixel_bearings
from ..model import Predictor
from .job import Job, resolve_job
from .points import SparsePoints, read_points
from .run import run_job
from .settings import OdometrySettings
from .write import SUMMARY_FILE

__all__ = ["RidePoses", "export_colmap", "export_rerun", "ride_poses"]


@dataclass
class _Frame:
    index: int
    name: str
    time: float
    rgb: np.ndarray  # uint8 [H,W,3] of ``camera``, the source
    camera: Camera
    c2w: np.ndarray  # [4,4]
    depth: np.ndarray  # [h,w] of ``depth_camera``, in the trajectory's unit
    depth_camera: Camera
    mask: np.ndarray | None  # [h,w], 0 on an occluder
    small: torch.Tensor | None  # [3,h,w] the frame at the network's size, in [0, 1] (None: not asked for)


@dataclass
class RidePoses:
    """A ride posed by its odometry, for an export.

    Attributes:
        job: the resolved run (ride, networks, plan, mask, depth source).
        c2w: the camera-to-world poses ``[M,4,4]`` in ``unit``.
        unit: the trajectory's unit (``"metres"``, ``"network units"``, ...).
        metres_per_unit: the scale from the network's unit (``None``: none applied).
        depth: the folder of every frame's depth in ``unit`` (``None``: predicted again as the frames
            are read).
        points: the bundle adjustment's points and tracks, in ``unit`` (``None``: not adjusted).
    """

    job: Job
    c2w: np.ndarray
    unit: str
    metres_per_unit: float | None
    depth: Path | None
    points: SparsePoints | None = None

    def frames(self, small: bool = False) -> Iterator[_Frame]:
        """The ride's frames in order, each with its pose, depth and mask; ``small``: with the frame at the
        network's size too (made anyway for a frame whose depth is predicted again)."""
        job = self.job
        mask = None if job.mask is None else job.mask[0, 0].numpy()
        scale = np.float32(self.metres_per_unit or 1.0)
        n = 0
        for index, stem, when, rgb in job.ride.read():
            if index >= len(self.c2w):
                break
            saved = None if self.depth is None else self.depth / f"{stem}.npy"
            known = saved is not None and saved.is_file()
            image = None
            if small or not known:
                with torch.inference_mode():
                    image = job.images([rgb])
            if known:
                depth = load_depth(saved)
            else:
                depth = job.view_of(job.depth([index], image))[0, 0].cpu().numpy() * scale
            yield _Frame(
                index,
                stem,
                when,
                rgb,
                job.plan.camera,
                self.c2w[index],
                depth,
                job.camera,
                mask,
                None if image is None or not small else image[0].cpu(),
            )
            n += 1
        if n != len(self.c2w):
            raise CylsfmError(f"{job.ride.path}: {n} frames read for {len(self.c2w)} poses of its odometry")


def ride_poses(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str] | Predictor,
    work: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
    odometry: str | os.PathLike[str] | None = None,
) -> RidePoses:
    """The ride ``input`` posed for an export: the odometry run ``odometry`` when given (checked against
    its fingerprint), else run into ``work`` (with every frame's depth; a run already there with the same
    settings is reused, a killed one continued).

    Raises:
        CylsfmError: as :func:`cylsfm.odometry`; a model that does not see whole panoramas; an odometry
            output that is missing, unreadable, unfinished or made with other settings (naming them).
    """
    opt = settings or OdometrySettings()
    if odometry is None:
        opt = replace(opt, save_depth_maps=True)
    job = resolve_job(input, checkpoint, work if odometry is None else odometry, opt)
    if job.predictor.fov < 360:
        raise CylsfmError(
            f"{checkpoint}: the model sees {job.predictor.fov:g}-degree crops; exporting a ride needs 360"
        )
    if odometry is not None:
        return _given(job)
    result = run_job(job)
    points = _points(job, len(result.c2w)) if opt.adjusts else None
    return RidePoses(job, result.c2w, result.unit, result.metres_per_unit, result.depth, points)


def _points(job: Job, frames: int) -> SparsePoints:
    """The bundle adjustment's points of the run in ``job.out``."""
    return read_points(job.out / "points.npz", frames, job.plan.camera.size)


def _given(job: Job) -> RidePoses:
    """The poses of the odometry output ``job.out``, made with ``job``'s settings."""
    path = job.out / SUMMARY_FILE
    try:
        summary = json.loads(path.read_text())
        recorded, settings = summary["fingerprint"], summary["settings"]
    except FileNotFoundError:
        raise CylsfmError(f"{path}: not found; give a finished output of cylsfm odometry") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CylsfmError(f"{path}: not a summary of cylsfm odometry ({exc})") from None
    if recorded != job.fingerprint:
        mine = job.identity
        differ = sorted(k for k in set(mine) | set(settings) if mine.get(k) != settings.get(k))
        shown = "; ".join(f"{k}: {settings.get(k)!r} there, {mine.get(k)!r} here" for k in differ[:4])
        raise CylsfmError(
            f"{job.out}: that odometry was made with other settings ({shown}); give the same input, "
            "checkpoint and options, or leave --odometry out to run it again"
        )
    _, c2w = read_tum(job.out / "trajectory.txt")
    depth = job.out / "depth" if summary.get("depth_maps") else None
    points = _points(job, len(c2w)) if summary.get("bundle") else None
    return RidePoses(job, c2w, str(summary["unit"]), summary.get("metres_per_unit"), depth, points)


def export_colmap(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str] | Predictor,
    out: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
    views: ViewOptions | None = None,
    odometry: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """The ride ``input`` (a video, a folder of frames or a dataset sequence) as a COLMAP model in ``out``.

    The poses are those of the odometry run ``odometry`` (made with the same settings), else of one run
    with ``settings`` (and every frame's depth) into ``OUT/odometry`` (a run already there with the same
    settings is reused, a killed one continued). Writes ``OUT/images/``, ``OUT/sparse/0/``,
    ``OUT/transforms.json`` and ``OUT/sparse_pc.ply`` from the ride's frames, its trajectory and its points:
    with the bundle adjustment (``settings.adjusts``: by default with ``refine``), its triangulated points
    with the keypoints that saw them; else points made from the depth (metres with
    ``settings.camera_height``, else the network's units: the same unit as the trajectory).
    Returns a summary (``panoramas``, ``images``, ``points``, ``unit``).

    Raises:
        CylsfmError: as :func:`ride_poses`; pycolmap missing.
    """
    out = Path(out)
    writer = ColmapWriter(out, views)
    ride = ride_poses(input, checkpoint, out / "odometry", settings, odometry)
    for f in ride.frames():
        writer.add(f.name, f.rgb, f.camera, f.c2w, f.depth, f.depth_camera, f.mask)
    if ride.points is not None:  # the adjusted points with their keypoints, not points made from the depth
        sp = ride.points
        bearings = pixel_bearings(ride.job.plan.camera, torch.from_numpy(sp.uv)).numpy()
        writer.use_points(sp.xyz, sp.rgb, sp.frame, sp.point, bearings)
    return {**writer.finish(), "unit": ride.unit}


def export_rerun(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str] | Predictor,
    out: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
    points_per_frame: int = 4000,
    odometry: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """The ride ``input`` as a rerun recording ``out`` (``.rrd``), posed by the odometry run ``odometry``,
    else by one run (with every frame's depth) into ``OUT.odometry/`` beside it, reused as by
    :func:`export_colmap`. Returns ``{"frames", "unit", "path"}``.

    Raises:
        CylsfmError: as :func:`ride_poses`; rerun-sdk missing.
    """
    from ..export.rerun import RerunWriter

    out = Path(out)
    ride = ride_poses(input, checkpoint, out.with_name(out.name + ".odometry"), settings, odometry)
    writer = RerunWriter(out, points_per_frame, ride.unit)
    n = 0
    try:
        if ride.points is not None:
            writer.add_points(ride.points.xyz, ride.points.rgb)
        for f in ride.frames(small=True):
            colours = (f.small.permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()
            writer.add(f.index, f.time, f.rgb, f.c2w, f.depth, f.depth_camera, colours, f.mask)
            n += 1
        path = writer.finish()
    except BaseException:
        writer.abort()
        raise
    return {"frames": n, "unit": ride.unit, "path": str(path)}
