"""The scaling stage of :func:`cylsfm.odometry`: the unit of the ride's steps, and of its depth files.

The pose network's translations and the depth network's depth share one unknown unit ("network units").
With ``steady_height`` each step's length is first brought to one unit by the ground height fitted in
its two frames (:func:`~cylsfm.geometry.ground.steady_height_steps`, before the loops are closed); with
``camera_height`` the whole ride is scaled to metres by the ground fitted below the horizon in every
frame's depth (:func:`~cylsfm.geometry.ground.metric_scale`), and so are the depth files. Refined with
ground-truth depth (``depth_from``), the steps are in metres already. After the bundle adjustment each
frame's depth file is brought to the adjusted points it sees (:func:`~cylsfm.odometry.depth.point_factors`),
so that every frame's depth is in the trajectory's one unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..data.format import load_depth
from ..data.geometry import ride_geometry
from ..data.points import SparsePoints
from ..evaluate.pose_metrics import chain_poses
from ..geometry.ground import metric_scale, steady_height_steps
from .depth import RAW_DEPTH, DepthScale, point_factors, remove_raw_depth, scale_depth_files
from .state import STATE_FILE, State

if TYPE_CHECKING:
    from .job import Job

__all__ = ["Scaled", "scale_depth_maps", "scale_steps", "steady_steps"]


@dataclass
class Scaled:
    """The ride's steps in their final unit.

    Attributes:
        steps: ``T_{j->j+1}`` ``[M-1,4,4]``.
        unit: ``"metres"``, ``"metres (ground-truth depth)"`` or ``"network units"``.
        metres_per_unit: the scale applied to the network's unit (``None``: none).
        note: the trajectory file's header line on the unit.
    """

    steps: np.ndarray
    unit: str
    metres_per_unit: float | None
    note: str


def steady_steps(steps: np.ndarray, heights: np.ndarray, steady: bool) -> np.ndarray:
    """``steps [M-1,4,4]`` with their lengths in a steady camera height's unit when ``steady`` (from the
    ground heights ``[M]`` fitted in every frame), else as they are."""
    return steady_height_steps(steps, heights)[0] if steady else steps


def scale_steps(job: Job, state: State, steps: np.ndarray) -> Scaled:
    """The steps ``[M-1,4,4]`` in metres when the camera height is given (and the depth files with them),
    else as they are (see the module docstring)."""
    height = job.settings.camera_height
    if height is None:
        unit = job.depth.unit
        hint = "" if job.depth.truth else " (give the camera height for metres)"
        return Scaled(steps, unit, None, f"unit: {unit}{hint}")
    scale, used = metric_scale(np.asarray(state.heights), height)
    steps = steps * np.where(np.arange(4)[:, None] < 3, [1.0, 1.0, 1.0, scale], 1.0)  # translations in m
    note = (
        f"unit: metres (camera height {height:g} m over the ground fitted in {used} frames: "
        f"{scale:.6g} m per network unit)"
    )
    return Scaled(steps, "metres", scale, note)


def scale_depth_maps(
    job: Job, state: State, scaled: Scaled, points: SparsePoints | None
) -> DepthScale | None:
    """``OUT/depth/FRAME.npy`` in the trajectory's unit from the maps in network units, when they wait for
    it: each brought to the adjusted ``points`` it sees (in the trajectory's world and unit), else all by
    the one factor to metres. Idempotent (the raw maps are removed once every scaled one is written, which
    the state records). Returns the per-frame factors (``None`` without the points or the maps)."""
    opt = job.settings
    if not opt.save_depth_maps or not (opt.adjusts or opt.camera_height is not None):
        return None  # written in their unit by the tracking
    raw = job.out / RAW_DEPTH
    base = scaled.metres_per_unit or 1.0
    if points is not None and not state.rescaled:
        c2w = chain_poses(scaled.steps)
        geometry = ride_geometry(c2w, points, job.plan.camera)
        found = point_factors(geometry, job.view, lambda j: load_depth(raw / f"{state.stems[j]}.npy"), base)
        state.depth_factors, state.depth_points = found.factors, found.points
    measured = len(state.depth_factors) == len(state.stems)
    if not state.rescaled:
        scale_depth_files(raw, job.out / "depth", state.stems, state.depth_factors if measured else base)
        state.rescaled = True
        state.save(job.out / STATE_FILE)
    remove_raw_depth(raw)
    return DepthScale(state.depth_factors, state.depth_points) if measured else None
