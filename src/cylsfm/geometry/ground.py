"""Metric scale from the camera's height: the ground below the horizon, found in a depth map.

A monocular network's depth and motion share one unknown scale. A camera carried at a known height above
a ground that is roughly level (a car, a helmet, a hand-held pole) fixes it: :func:`ground_height` fits a
plane to the points seen well below the horizon and returns the camera's distance to it, in the depth's
unit; ``metres / that`` is the scale. The fit is robust (iteratively reweighted least squares that keeps
the points within 10% of the height of the plane), so kerbs, cars and walls low in the view count little.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError, check_shape
from .cameras import Camera

__all__ = ["MIN_GROUND_POINTS", "ground_height", "metric_scale", "steady_height_steps"]

#: The least number of points below the horizon a frame needs for a ground fit.
MIN_GROUND_POINTS = 50
#: Points this far below the horizon (degrees) or further are candidates for the ground.
_BELOW_DEG = 15.0


def _fit_one(points: np.ndarray) -> float:
    """Distance from the origin to the plane through ``points [N,3]`` (nan when it does not fit)."""
    height = float(np.median(points[:, 1]))
    if not height > 0:
        return math.nan
    normal = np.array([0.0, 1.0, 0.0])
    keep = np.ones(len(points), dtype=bool)
    for _ in range(5):
        keep = np.abs(points @ normal - height) < 0.1 * height
        if keep.sum() < MIN_GROUND_POINTS:
            return math.nan
        p = points[keep]
        centre = p.mean(0)
        _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
        n = vt[-1] if vt[-1, 1] > 0 else -vt[-1]
        if n[1] < math.cos(math.radians(30)):  # not a floor: more than 30 degrees from level
            return math.nan
        normal, height = n, float(centre @ n)
    return height if height > 0 else math.nan


def ground_height(depth: Tensor, camera: Camera) -> Tensor:
    """The camera's height above the ground seen in each depth map.

    Args:
        depth: ``[B,1,H,W]`` depth of the camera model (any unit; ``<= 0``: unknown).
        camera: its camera (axes: x right, y down, z forward; the ground is below, at ``+y``).

    Returns:
        ``[B]`` float64 heights in the depth's unit, ``nan`` for a frame without a ground fit (fewer than
        :data:`MIN_GROUND_POINTS` points more than 15 degrees below the horizon, or no level plane among
        them).
    """
    check_shape(depth, "B,1,H,W", "depth")
    points = camera.unproject(depth.float().clamp(min=0))  # [B,3,H,W]
    rng = points.square().sum(1).sqrt()  # the range; vector_norm(dim=1) is ~200x slower on the CPU
    below = (points[:, 1] > rng * math.sin(math.radians(_BELOW_DEG))) & (depth[:, 0] > 0)
    out = []
    for b in range(depth.shape[0]):
        sel = points[b].permute(1, 2, 0)[below[b]].double().cpu().numpy()
        out.append(_fit_one(sel) if len(sel) >= MIN_GROUND_POINTS else math.nan)
    return torch.tensor(out, dtype=torch.float64)


def metric_scale(heights: np.ndarray, camera_height: float) -> tuple[float, int]:
    """``(metres per depth unit, frames used)``: ``camera_height`` over the median of the frames' fitted
    heights (``nan`` entries skipped).

    Raises:
        InputError: ``camera_height`` not a positive number, or no frame with a ground fit.
    """
    if not (math.isfinite(camera_height) and camera_height > 0):
        raise InputError(f"camera height must be a positive number of metres, got {camera_height}")
    fitted, median = _fitted(
        heights, "the camera height cannot set the scale; leave out the camera height (network units)"
    )
    return camera_height / median, int(fitted.sum())


def _fitted(heights: np.ndarray, consequence: str) -> tuple[np.ndarray, float]:
    """``(frames with a ground fit [M] bool, their median height)``; ``InputError`` naming ``consequence``
    when no frame has one."""
    h = np.asarray(heights, dtype=np.float64)
    fitted = np.isfinite(h) & (h > 0)
    if not fitted.any():
        raise InputError(f"no frame shows a level ground below the horizon, so {consequence}")
    return fitted, float(np.median(h[fitted]))


def steady_height_steps(steps: np.ndarray, heights: np.ndarray) -> tuple[np.ndarray, int]:
    """The steps' lengths brought to one unit by a camera that stays at one height above the ground.

    The depth's unit wanders from frame to frame; the ground height fitted in each frame measures it. Each
    step's translation is divided by the mean of its two frames' heights over the median height of the
    ride (a frame without a ground fit counts as the median), so that every step is in the unit in which
    the camera's height is the ride's median; rotations are kept.

    Args:
        steps: relative poses ``[M-1, 4, 4]`` (frame ``i+1`` in frame ``i``), translations in the depth's unit.
        heights: fitted ground heights ``[M]`` in the same unit, ``nan`` where none was fitted.

    Returns:
        ``(steps [M-1, 4, 4], frames with a ground fit)``.

    Raises:
        InputError: ``heights`` not one per frame, or no frame with a ground fit.
    """
    steps = np.asarray(steps, dtype=np.float64)
    h = np.asarray(heights, dtype=np.float64)
    if steps.ndim != 3 or steps.shape[1:] != (4, 4) or h.shape != (len(steps) + 1,):
        raise InputError(f"steady height: {len(steps)} steps need {len(steps) + 1} heights, got {h.shape}")
    fitted, median = _fitted(
        h, "the steps cannot be brought to the camera height's unit; leave out the steady height"
    )
    ratio = np.where(fitted, h / median, 1.0)
    out = steps.copy()
    out[:, :3, 3] /= ((ratio[:-1] + ratio[1:]) / 2)[:, None]
    return out, int(fitted.sum())
