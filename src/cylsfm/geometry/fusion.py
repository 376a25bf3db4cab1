"""A ride's depth maps fused across neighbouring frames by their poses.

Each frame's depth ``D_t`` is checked against the depth that its neighbours ``s`` saw at the same points:
a target pixel is lifted with ``D_t``, moved into frame ``s`` and projected there; ``D_s`` sampled at that
place (bilinearly, across the seam of a full panorama) says how far the point is from ``s``, and the
target's depth is scaled by the ratio of that to the depth the lifted point has from ``s``:

    ``candidate_s = D_t * D_s(project(T_ts P_t)) / depth_s(T_ts P_t)``

(a first-order correction along the target's ray: exact when the two frames agree, and as far off as
they disagree otherwise). The fused depth is the median of ``D_t`` and every candidate, in log depth, so
that a neighbour that sees another surface (an occluder, a moving car) is outvoted; its spread, the
median absolute deviation of the log candidates around it, says how far the frames agree. A pixel that
fewer than ``min_views`` frames see keeps no fused depth (0).

Frames whose depth errors differ (a network's depth is wrong differently in each frame away from
textured places) are brought towards what their neighbours agree on; an error that every frame shares
stays.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import InputError, check_shape
from .cameras import Camera
from .pose import invert
from .warp import sample_image, transform_points

__all__ = ["fuse_depth"]


def fuse_depth(
    depths: Tensor, c2w: Tensor, camera: Camera, neighbours: int = 3, min_views: int = 3, chunk: int = 32
) -> tuple[Tensor, Tensor]:
    """Fuse each frame's depth with its ``neighbours`` frames on either side (see the module docstring).

    Args:
        depths: ``[M,1,H,W]`` the ride's depth maps, in one unit along the ride (the poses'), in the camera
            model's depth; values ``<= 0`` are unknown.
        c2w: ``[M,4,4]`` camera-to-world poses of the frames, in the depths' unit.
        camera: the camera of the maps (size ``W x H``).
        neighbours: frames on either side compared (``>= 1``).
        min_views: the fewest frames (the target included) that must see a pixel for it to be fused.
        chunk: frames fused at once (memory: ``chunk * (2 neighbours + 1)`` maps; the result is the same).

    Returns:
        ``(fused [M,1,H,W], spread [M,1,H,W])``: the fused depth (0 where unknown) and the spread of the
        log depths it was fused from (0 where unknown), float32.

    Frames that agree keep their depth:

    >>> from cylsfm.geometry import CylindricalCamera
    >>> cam = CylindricalCamera.full(16, 4)
    >>> c2w = torch.eye(4).repeat(3, 1, 1)
    >>> c2w[:, 0, 3] = torch.tensor([0.0, 0.1, 0.2])  # a step of 0.1 to the right each frame
    >>> fused, spread = fuse_depth(torch.full((3, 1, 4, 16), 5.0), c2w, cam, neighbours=1, min_views=1)
    >>> bool(((fused[1] - 5.0).abs() < 0.3).all()), fused.shape
    (True, torch.Size([3, 1, 4, 16]))
    """
    check_shape(depths, "M,1,H,W", "depths")
    m, _, h, w = depths.shape
    check_shape(c2w, f"{m},4,4", "c2w")
    if (w, h) != camera.size:
        raise InputError(f"depths are {w}x{h} but the camera is {camera.width}x{camera.height}")
    if neighbours < 1 or min_views < 1 or chunk < 1:
        raise InputError(
            f"neighbours, min_views and chunk must be at least 1, got {neighbours}, {min_views}, {chunk}"
        )
    with torch.autocast(device_type=depths.device.type, enabled=False):
        d, poses = depths.float(), c2w.double()
        parts = [
            _fuse_chunk(d, poses, camera, neighbours, min_views, c0, min(c0 + chunk, m))
            for c0 in range(0, m, chunk)
        ]
    fused, spread = (torch.cat(p, 0) for p in zip(*parts, strict=True))
    return fused, spread


def _fuse_chunk(
    d: Tensor, poses: Tensor, camera: Camera, neighbours: int, min_views: int, c0: int, c1: int
) -> tuple[Tensor, Tensor]:
    """:func:`fuse_depth` of the target frames ``c0 .. c1 - 1`` of the ride's depths ``d`` ``[M,1,H,W]``
    (float32) posed by ``poses`` ``[M,4,4]`` (float64)."""
    m, _, h, w = d.shape
    known = d[c0:c1] > 0
    logs = torch.full((c1 - c0, 2 * neighbours + 1, h, w), float("nan"), device=d.device)
    logs[:, neighbours] = torch.where(known, d[c0:c1].clamp(min=1e-6).log(), torch.nan)[:, 0]
    points = camera.unproject(d[c0:c1].clamp(min=1e-6))
    for k, offset in enumerate(range(-neighbours, neighbours + 1)):
        first, end = max(c0, -offset), min(c1, m - offset)
        if offset == 0 or first >= end:  # the target itself, or no frame that far away
            continue
        t = torch.arange(first, end, device=d.device)
        s, i = t + offset, t - c0
        to_source = (invert(poses[s]) @ poses[t]).float()  # T_target_to_source
        moved = transform_points(to_source, points[i])
        seen = camera.depth_of(moved)
        there, valid = sample_image(d[s], camera.project(moved), camera.wraps)
        ok = valid & camera.projectable(moved) & known[i] & (seen > 1e-6) & (there > 0)
        candidate = d[t] * there / seen.clamp(min=1e-6)
        logs[i, k] = torch.where(ok, candidate.clamp(min=1e-6).log(), torch.nan)[:, 0]
    views = torch.isfinite(logs).sum(1, keepdim=True)
    median = torch.nanmedian(logs, 1, keepdim=True).values
    spread = torch.nanmedian((logs - median).abs(), 1, keepdim=True).values
    fused_ok = (views >= min_views) & known
    fused = torch.where(fused_ok, median.exp(), torch.zeros_like(median))
    return fused, torch.where(fused_ok, spread, torch.zeros_like(spread))
