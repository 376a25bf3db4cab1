"""Which way the camera faces on its mount: the azimuth of the direction of travel in the panorama.

A pose network trained on rides filmed facing forward reads the motion of a camera mounted turned (on the
side of a helmet, across a car roof) badly: its translation keeps pointing where the training rides went.
:func:`mount_yaw` finds the direction of travel from the images and their depth alone: for pairs of frames
a few frames apart it aligns the source to the target (:func:`~cylsfm.geometry.align.align`) from
``DIRECTIONS`` starting directions of travel around the circle, keeps the one that aligns best, and takes
the robust (circular, weighted) median of the pairs' directions. The frames can then be turned (a yaw roll)
so that the network sees the camera facing its motion.

The search among the directions runs on the frames at half their width and height (a quarter of the
work: telling which way a camera went needs no fine detail); only each pair's best direction is then
aligned at full size, from where the half-size search left it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from ..geometry import Camera, compass_yaw, yaw_matrix
from ..geometry.align import AlignConfig, align
from ..geometry.photometric import half_size, photometric_costs

__all__ = ["DIRECTIONS", "MOUNT_AGREEMENT", "STRAIGHT_AHEAD_DEG", "Mount", "mount_summary", "mount_yaw"]

#: Starting directions of travel tried per pair, evenly around the circle.
DIRECTIONS = 8
#: Frames between the two frames of a pair (more parallax than consecutive frames).
GAP = 3
#: Pairs aligned at most.
PAIRS = 12
#: The direction of travel found is used when at least this weighted fraction of the pairs agree with it.
MOUNT_AGREEMENT = 0.5
#: A direction of travel found within this many degrees of straight ahead leaves the frames as they are
#: (the network reads them as trained: a camera facing its motion); turning them by a column or two
#: changed no result (RESULTS.md) and would cost the search's windows, read again turned.
STRAIGHT_AHEAD_DEG = 2.0


@dataclass(frozen=True)
class Mount:
    """The direction of travel found by :func:`mount_yaw`.

    Attributes:
        yaw: its azimuth in radians (``atan2(x, z)`` in the camera frame: 0 straight ahead, ``+pi/2`` right).
        agreement: the weighted fraction of the pairs whose direction lies within 30 degrees of it.
        pairs: how many pairs were aligned.
    """

    yaw: float
    agreement: float
    pairs: int


def _starts(tgt: Tensor, src: Tensor, length: float, directions: int, mask: Tensor | None) -> Tensor:
    """``[B,K,4,4]``: the compass's yaw with a step of ``length`` towards each of ``K`` azimuths."""
    b = tgt.shape[0]
    rot = yaw_matrix(compass_yaw(tgt.float(), src.float(), mask), dtype=torch.float64)  # [B,3,3]
    az = torch.arange(directions, dtype=torch.float64) * (2 * math.pi / directions)
    centres = length * torch.stack((torch.sin(az), torch.zeros_like(az), torch.cos(az)), -1)  # [K,3]
    out = torch.eye(4, dtype=torch.float64).repeat(b, directions, 1, 1)
    out[..., :3, :3] = rot[:, None]
    out[..., :3, 3] = -(rot[:, None] @ centres[None, :, :, None])[..., 0]  # t = -R c
    return out.to(tgt.device)


def _circular_median(angles: Tensor, weights: Tensor) -> float:
    """The angle among ``angles`` with the least weighted sum of angular distances to all of them."""
    diff = torch.remainder(angles[:, None] - angles[None] + math.pi, 2 * math.pi) - math.pi
    return float(angles[(diff.abs() * weights[None]).sum(1).argmin()])


def _best_direction(
    tgt: Tensor,
    src: Tensor,
    depth: Tensor,
    starts: Tensor,
    camera: Camera,
    config: AlignConfig,
    mask: Tensor | None,
) -> Tensor:
    """Each pair aligned from each of its ``K`` starts ``[B,K,4,4]``: the pose that fits best ``[B,4,4]``."""
    b, k = starts.shape[:2]
    res = align(
        tgt.repeat_interleave(k, 0),
        src.repeat_interleave(k, 0),
        depth.repeat_interleave(k, 0),
        starts.flatten(0, 1),
        camera,
        config=config,
        mask=mask,
    )
    found = res.poses.view(b, k, 4, 4)
    costs = photometric_costs(tgt, src, depth, found, camera, mask=mask)  # [B,K]
    return found[torch.arange(b), costs.argmin(1)]


def mount_yaw(
    images: Tensor,
    depth: Tensor,
    camera: Camera,
    step_length: float,
    config: AlignConfig | None = None,
    gap: int = GAP,
    pairs: int = PAIRS,
    directions: int = DIRECTIONS,
    mask: Tensor | None = None,
    halve: bool = True,
) -> Mount | None:
    """The azimuth of the direction of travel over consecutive frames of a full-panorama ride.

    Args:
        images: frames ``[N,3,H,W]`` in [0, 1], in order, of a full panorama ``camera``.
        depth: their depth ``[N,1,H,W]`` (any unit).
        step_length: the length of one frame's step in the depth's unit (e.g. the pose network's).
        config: the alignment's settings; gap: frames between a pair's two frames; pairs: at most this
            many pairs, spread over the frames; directions: starting directions per pair.
        mask: ``[1,1,H,W]``: 1 where the scene is seen, 0 on an occluder fixed to the camera (``None``:
            every pixel); the compass and the alignment leave the occluder out.
        halve: search among the directions at half size and align the best at full size (``False``: the
            whole search at full size, four times the work, for comparison).

    Returns:
        The :class:`Mount`, or ``None`` for too few frames (``N <= gap``).
    """
    n = images.shape[0]
    if n <= gap:
        return None
    first = torch.linspace(0, n - 1 - gap, min(pairs, n - gap)).round().long().unique()
    tgt, src, d = images[first], images[first + gap], depth[first]
    starts = _starts(tgt, src, step_length * gap, directions, mask)
    config = config or AlignConfig()
    small = half_size(tgt, src, d, camera, mask) if halve else None
    if small is None:  # too small to halve: the search at full size
        best = _best_direction(tgt, src, d, starts, camera, config, mask)
    else:
        tgt_half, src_half, d_half, cam_half, mask_half = small
        coarse = replace(config, levels=max(1, config.levels - 1))
        best = _best_direction(tgt_half, src_half, d_half, starts, cam_half, coarse, mask_half)
        best = align(tgt, src, d, best, camera, config=replace(config, levels=1), mask=mask).poses
    centres = -(best[:, :3, :3].transpose(1, 2) @ best[:, :3, 3:])[..., 0]
    heading = torch.atan2(centres[:, 0], centres[:, 2])
    weight = centres[:, [0, 2]].norm(dim=1)
    yaw = _circular_median(heading, weight)
    close = (torch.remainder(heading - yaw + math.pi, 2 * math.pi) - math.pi).abs() < math.radians(30)
    agreement = float((weight * close).sum() / weight.sum().clamp(min=1e-12))
    return Mount(yaw, agreement, len(first))


def mount_summary(given: float | None, found: tuple[float, float, int]) -> dict[str, Any] | None:
    """The direction of travel the pose network was turned to, as ``odometry.json`` says it (``None``: the
    frames as they are).

    Args:
        given: the direction given by the user (radians), or ``None``.
        found: ``(yaw in radians, agreement, pairs)`` as the tracker found it (yaw ``nan``: not found).
    """
    if given is not None:
        return {"yaw_deg": math.degrees(given), "agreement": None, "pairs": 0, "how": "given"}
    yaw, agreement, pairs = found
    if not math.isfinite(yaw):
        return None
    if math.isfinite(agreement) and yaw == 0.0 and agreement < MOUNT_AGREEMENT:
        how = f"not found: {pairs} pairs of frames disagree ({agreement:.0%} agree); taken as straight ahead"
    else:
        how = f"found in {pairs} pairs of frames, {agreement:.0%} agree"
        if abs(math.degrees(yaw)) < STRAIGHT_AHEAD_DEG:
            how += f"; within {STRAIGHT_AHEAD_DEG:g} degrees of straight ahead, the frames not turned"
    return {"yaw_deg": math.degrees(yaw), "agreement": agreement, "pairs": pairs, "how": how}
