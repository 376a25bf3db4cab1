"""``cylsfm export colmap``: a ride's odometry as a COLMAP model and a nerfstudio ``transforms.json``
(:mod:`cylsfm.export.colmap`), for Gaussian splatting and NeRF trainers."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..data.format import load_depth
from ..errors import CylsfmError
from ..export.colmap import ColmapWriter, ViewOptions
from ..model import Predictor
from ..model.plan import network_mask
from .frames import open_ride
from .run import _mask_file, _plan, odometry
from .settings import OdometrySettings

__all__ = ["export_colmap"]


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
    opt = replace(settings or OdometrySettings(), save_depth_maps=True)
    out = Path(out)
    result = odometry(input, checkpoint, out / "odometry", opt)
    ride = open_ride(input, opt.fps, opt.stride)
    predictor = Predictor.from_checkpoint(checkpoint, opt.device)
    if predictor.fov < 360:
        raise CylsfmError(
            f"{checkpoint}: the model sees {predictor.fov:g}-degree crops; export colmap needs 360"
        )
    plan = _plan(ride, predictor, opt.camera)
    net_cam = plan.network_input.resized(*predictor.size)
    mask_file = _mask_file(ride, opt.mask)
    mask = None
    if mask_file is not None:
        mask = network_mask(mask_file, ride.size, plan, predictor.size)[0, 0].numpy()
    pose_of = dict(zip(result.frames, result.c2w, strict=True))
    writer = ColmapWriter(out, views)
    for _, stem, _, rgb in ride.read():
        depth = load_depth(out / "odometry" / "depth" / f"{stem}.npy")
        writer.add(stem, rgb, plan.camera, pose_of[stem], depth, net_cam, mask)
    return {**writer.finish(), "unit": result.unit}
