"""``cylsfm export colmap`` and ``cylsfm export rerun``: a ride's odometry, its frames and their depth for
the 3D tools users move on to: a COLMAP model and a nerfstudio ``transforms.json`` (for Gaussian splatting
and NeRF trainers, :mod:`cylsfm.export.colmap`), a rerun recording (:mod:`cylsfm.export.rerun`)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.format import load_depth
from ..errors import CylsfmError
from ..export.colmap import ColmapWriter, ViewOptions
from ..geometry import Camera
from ..model import Predictor
from ..model.plan import network_images, network_mask
from .frames import open_ride
from .run import odometry, ride_mask, ride_plan
from .settings import OdometrySettings
from .track import network_size

__all__ = ["export_colmap", "export_rerun"]


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


def _ride(
    input: Any, checkpoint: Any, work: Path, settings: OdometrySettings | None
) -> tuple[str, Iterator[_Frame], Any]:
    """Run the odometry (with every frame's depth) into ``work`` and give ``(unit, the frames, the
    predictor and plan)``."""
    opt = replace(settings or OdometrySettings(), save_depth_maps=True)
    result = odometry(input, checkpoint, work, opt)
    ride = open_ride(input, opt.fps, opt.stride)
    predictor = Predictor.from_checkpoint(checkpoint, opt.device, amp=opt.amp)
    if predictor.fov < 360:
        raise CylsfmError(
            f"{checkpoint}: the model sees {predictor.fov:g}-degree crops; exporting a ride needs 360"
        )
    plan = ride_plan(ride, predictor, opt.camera)
    net_cam = plan.network_input.resized(*predictor.size)
    mask_file = ride_mask(ride, opt.mask)
    mask = (
        None if mask_file is None else network_mask(mask_file, ride.size, plan, predictor.size)[0, 0].numpy()
    )
    pose_of = dict(zip(result.frames, result.c2w, strict=True))

    def frames() -> Iterator[_Frame]:
        for index, stem, when, rgb in ride.read():
            depth = load_depth(work / "depth" / f"{stem}.npy")
            yield _Frame(index, stem, when, rgb, plan.camera, pose_of[stem], depth, net_cam, mask)

    return result.unit, frames(), (predictor, plan)


def export_colmap(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str],
    out: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
    views: ViewOptions | None = None,
) -> dict[str, Any]:
    """The ride ``input`` (a video, a folder of frames or a dataset sequence) as a COLMAP model in ``out``.

    Runs :func:`cylsfm.odometry` with ``settings`` (and every frame's depth) into ``OUT/odometry`` (a run
    already there with the same settings is reused, a killed one continued), then writes ``OUT/images/``,
    ``OUT/sparse/0/``, ``OUT/transforms.json`` and ``OUT/sparse_pc.ply`` from the ride's frames, its
    trajectory and the depth (metres with ``settings.camera_height``, else the network's units: the same
    unit as the trajectory). Returns a summary (``panoramas``, ``images``, ``points``, ``unit``).

    Raises:
        CylsfmError: as :func:`cylsfm.odometry`; a model that does not see whole panoramas; pycolmap
            missing.
    """
    out = Path(out)
    writer = ColmapWriter(out, views)
    unit, frames, _ = _ride(input, checkpoint, out / "odometry", settings)
    for f in frames:
        writer.add(f.name, f.rgb, f.camera, f.c2w, f.depth, f.depth_camera, f.mask)
    return {**writer.finish(), "unit": unit}


def export_rerun(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str],
    out: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
    points_per_frame: int = 4000,
) -> dict[str, Any]:
    """The ride ``input`` as a rerun recording ``out`` (``.rrd``; the odometry, with every frame's depth,
    in ``OUT.odometry/`` beside it, reused as by :func:`export_colmap`). Returns ``{"frames", "unit",
    "path"}``.

    Raises:
        CylsfmError: as :func:`cylsfm.odometry`; a model that does not see whole panoramas; rerun-sdk
            missing.
    """
    from ..export.rerun import RerunWriter

    out = Path(out)
    unit, frames, (predictor, plan) = _ride(
        input, checkpoint, out.with_name(out.name + ".odometry"), settings
    )
    writer = RerunWriter(out, points_per_frame, unit)
    n = 0
    try:
        for f in frames:
            with torch.inference_mode():
                small = network_size(network_images([f.rgb], plan, predictor.device), predictor.size)
            colours = (small[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().cpu().numpy()
            writer.add(f.index, f.time, f.rgb, f.c2w, f.depth, f.depth_camera, colours, f.mask)
            n += 1
        path = writer.finish()
    except BaseException:
        writer.abort()
        raise
    return {"frames": n, "unit": unit, "path": str(path)}
