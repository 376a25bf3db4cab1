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

__all__ = ["MIN_GROUND_POINTS", "above_ground", "ground_height", "ground_plane", "metric_scale"]

#: The least number of points below the horizon a frame needs for a ground fit.
MIN_GROUND_POINTS = 50
#: Points this far below the horizon (degrees) or further are candidates for the ground.
_BELOW_DEG = 15.0


def _fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The plane through ``points [N,3]``: its unit normal (pointing down, ``+y``) and the distance from the
    origin to it (nan when it does not fit)."""
    normal = np.array([0.0, 1.0, 0.0])
    height = float(np.median(points[:, 1]))
    if not height > 0:
        return normal, math.nan
    keep = np.ones(len(points), dtype=bool)
    for _ in range(5):
        keep = np.abs(points @ normal - height) < 0.1 * height
        if keep.sum() < MIN_GROUND_POINTS:
            return normal, math.nan
        p = points[keep]
        centre = p.mean(0)
        _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
        n = vt[-1] if vt[-1, 1] > 0 else -vt[-1]
        if n[1] < math.cos(math.radians(30)):  # not a floor: more than 30 degrees from level
            return normal, math.nan
        normal, height = n, float(centre @ n)
    return normal, (height if height > 0 else math.nan)


def ground_plane(depth: Tensor, camera: Camera) -> tuple[Tensor, Tensor]:
    """The ground seen in each depth map: a plane ``n . p = height`` in the camera's frame.

    Args:
        depth: ``[B,1,H,W]`` depth of the camera model (any unit; ``<= 0``: unknown).
        camera: its camera (axes: x right, y down, z forward; the ground is below, at ``+y``).

    Returns:
        ``(normals [B,3], heights [B])`` float64: the plane's unit normal (pointing down) and the camera's
        distance to it in the depth's unit; height ``nan`` for a frame without a ground fit (fewer than
        :data:`MIN_GROUND_POINTS` points more than 15 degrees below the horizon, or no plane within 30
        degrees of level among them).
    """
    check_shape(depth, "B,1,H,W", "depth")
    points = camera.unproject(depth.float().clamp(min=0))  # [B,3,H,W]
    rng = torch.linalg.vector_norm(points, dim=1)
    below = (points[:, 1] > rng * math.sin(math.radians(_BELOW_DEG))) & (depth[:, 0] > 0)
    normals, heights = [], []
    for b in range(depth.shape[0]):
        sel = points[b].permute(1, 2, 0)[below[b]].double().cpu().numpy()
        n, h = _fit_plane(sel) if len(sel) >= MIN_GROUND_POINTS else (np.array([0.0, 1.0, 0.0]), math.nan)
        normals.append(n)
        heights.append(h)
    return torch.tensor(np.stack(normals), dtype=torch.float64), torch.tensor(heights, dtype=torch.float64)


def ground_height(depth: Tensor, camera: Camera) -> Tensor:
    """The camera's height above the ground seen in each depth map (:func:`ground_plane`'s heights).

    Args:
        depth: ``[B,1,H,W]`` depth of the camera model (any unit; ``<= 0``: unknown).
        camera: its camera.

    Returns:
        ``[B]`` float64 heights in the depth's unit, ``nan`` for a frame without a ground fit.
    """
    return ground_plane(depth, camera)[1]


def above_ground(
    depth: Tensor, camera: Camera, normals: Tensor, heights: Tensor, margin: float = 0.05
) -> Tensor:
    """Depth with nothing below the ground: each pixel whose ray meets the ground plane is brought no further
    than where it meets it (times ``1 + margin``); a point beyond would be under the floor.

    A network's depth is least sure on wide open ground far away, where it may put the ground too far;
    the plane fitted to the near ground (:func:`ground_plane`) bounds it there. Pixels above the plane's
    horizon, unknown depth (``<= 0``) and frames without a fit (height ``nan``) are left as they are.

    Args:
        depth: ``[B,1,H,W]`` depth of the camera model (any unit).
        camera: its camera.
        normals: ``[B,3]`` the planes' unit normals (pointing down), ``heights``: ``[B]`` the camera's
            distance to them (the depth's unit), as :func:`ground_plane` returns them.
        margin: the fraction beyond the plane a point may lie (the plane's own uncertainty).

    Returns:
        ``[B,1,H,W]`` the depth, bounded.

    Example:
        >>> from cylsfm.geometry import CylindricalCamera
        >>> cam = CylindricalCamera.full(64, 16)
        >>> far = torch.full((1, 1, 16, 64), 100.0)
        >>> bounded = above_ground(far, cam, torch.tensor([[0.0, 1.0, 0.0]]), torch.tensor([1.0]))
        >>> bool(bounded[0, 0, -1].max() < 100), bool(bounded[0, 0, 0].min() == 100)
        (True, True)
    """
    check_shape(depth, "B,1,H,W", "depth")
    check_shape(normals, "B,3", "normals")
    rays = camera.unproject(torch.ones_like(depth, dtype=torch.float32))  # [B,3,H,W]: a point at depth 1
    n = normals.to(rays)
    down = (rays * n[:, :, None, None]).sum(1, keepdim=True)  # [B,1,H,W]: how far down each ray heads
    h = heights.to(rays)[:, None, None, None]
    meets = (down > 1e-6) & torch.isfinite(h) & (depth > 0)
    bound = torch.where(meets, h * (1 + margin) / down.clamp(min=1e-6), torch.full_like(down, math.inf))
    return torch.minimum(depth, bound.to(depth.dtype))


def metric_scale(heights: np.ndarray, camera_height: float) -> tuple[float, int]:
    """``(metres per depth unit, frames used)``: ``camera_height`` over the median of the frames' fitted
    heights (``nan`` entries skipped).

    Raises:
        InputError: ``camera_height`` not a positive number, or no frame with a ground fit.
    """
    if not (math.isfinite(camera_height) and camera_height > 0):
        raise InputError(f"camera height must be a positive number of metres, got {camera_height}")
    h = np.asarray(heights, dtype=np.float64)
    h = h[np.isfinite(h) & (h > 0)]
    if not len(h):
        raise InputError(
            "no frame shows a level ground below the horizon, so the camera height cannot set the scale; "
            "leave out the camera height (network units)"
        )
    return camera_height / float(np.median(h)), len(h)
