"""The visual compass: the yaw between two full panoramas, read in closed form as a circular column shift.

A turn of a 360° camera about its vertical axis shifts its cylindrical panorama circularly by
``W * yaw / (2 pi)`` columns (:func:`cylsfm.geometry.roll_columns`); a forward motion mostly stretches
the view ahead and squeezes the view behind, which leaves that shift where it is. So the shift that best
aligns two frames of a ride measures the camera's turn between them without depth, training or features.
It is found by phase correlation along the width axis: the cross-power spectrum of the two images' column
gradients, summed over rows and colour channels and normalised to unit magnitude, is a pure phase ramp
``exp(-2 pi i k s / W)`` for a pure shift ``s``; its inverse transform peaks at ``s``. The integer peak is
refined to a fraction of a column by the slope of the residual phase over the low frequencies (exact for a
pure shift).

A mask fixed to the camera (a helmet or a mount, in the same pixels of both frames) would pull the shift to
zero; with ``mask`` the column gradients touching it are left out (set to zero in both images), so the
occluder adds nothing to the cross-power spectrum.

The compass learns nothing: in the evaluations it is the reference that a pose network's rotation must
beat, and it can initialise or check a network's yaw.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import InputError, ShapeError, check_shape

__all__ = ["column_shift", "compass_yaw", "compass_yaws", "window_yaws"]


def _spectrum(x: Tensor, mask: Tensor | None = None) -> Tensor:
    """Column-gradient spectrum ``[B, C*H, W//2+1]`` of images ``[B, C, H, W]`` (periodic width); with
    ``mask`` ``[B or 1, 1, H, W]`` only the differences between two pixels of the mask."""
    x = x.to(torch.float64)
    grad = x - torch.roll(x, 1, dims=-1)  # the difference across the seam included: circular
    if mask is not None:
        m = mask.to(device=x.device, dtype=torch.bool)
        grad = grad * (m & torch.roll(m, 1, dims=-1))
    return torch.fft.rfft(grad.flatten(1, 2), dim=-1)


def column_shift(
    a: Tensor,
    b: Tensor,
    low_band: float = 0.125,
    mask: Tensor | None = None,
    near: Tensor | None = None,
    within: float | Tensor | None = None,
) -> Tensor:
    """The circular column shift ``s`` with ``b ≈ roll_columns(a, s)``, to a fraction of a column.

    Args:
        a: panoramas ``[B, C, H, W]`` (any value range), full 360° width.
        b: panoramas of the same shape.
        low_band: fraction of the width's frequencies (from the lowest) whose phase refines the integer peak.
        mask: ``[B, 1, H, W]`` or ``[1, 1, H, W]``: 1 (True) where the scene is seen, 0 on an occluder fixed
            to the camera; ``None``: every pixel.
        near, within: ``[B]`` shifts (columns) and the largest distance from them (columns, a number or
            ``[B]``): only the peaks within ``within`` of ``near`` (circularly) are considered, e.g. a
            prior from odometry that tells a street seen the other way round from the same street behind
            the camera; ``None``: every shift.

    Returns:
        ``[B]`` shifts in columns (float64), in ``[-W/2, W/2)``.

    >>> a = torch.rand(1, 3, 8, 64)
    >>> round(float(column_shift(a, torch.roll(a, -5, dims=-1))), 6)
    -5.0
    """
    check_shape(a, "B,C,H,W", "a")
    if b.shape != a.shape:
        raise ShapeError(f"column_shift: b {tuple(b.shape)} and a {tuple(a.shape)} differ in shape")
    if mask is not None and (
        mask.dim() != 4
        or mask.shape[1] != 1
        or mask.shape[-2:] != a.shape[-2:]
        or mask.shape[0] not in (1, a.shape[0])
    ):
        raise ShapeError(f"column_shift: mask {tuple(mask.shape)} does not fit images {tuple(a.shape)}")
    cross = (_spectrum(a, mask).conj() * _spectrum(b, mask)).sum(1)  # [B, W//2+1]: |A|^2 e^{-2pi i k s/W}
    return _shift_of(cross, a.shape[-1], low_band, near, within)


def _shift_of(
    cross: Tensor,
    width: int,
    low_band: float = 0.125,
    near: Tensor | None = None,
    within: float | Tensor | None = None,
) -> Tensor:
    """The shifts ``[B]`` (columns) of the cross-power spectra ``cross`` ``[B, W//2+1]`` of panoramas
    ``width`` wide (see :func:`column_shift`)."""
    cross = cross.clone()
    cross[:, 0] = 0
    phase = cross / cross.abs().clamp_min(1e-12)
    score = torch.fft.irfft(phase, n=width, dim=-1)  # [B, W]: the correlation at each integer shift
    if near is not None:
        if within is None:
            raise InputError("column_shift: near needs within")
        shifts = torch.arange(width, dtype=torch.float64, device=cross.device)
        centre = near.to(device=cross.device, dtype=torch.float64).reshape(-1, 1)
        apart = torch.remainder(shifts - centre + width / 2, width) - width / 2
        limit = torch.as_tensor(within, dtype=torch.float64, device=cross.device).reshape(-1, 1)
        score = torch.where(apart.abs() <= limit.clamp(min=0.5), score, torch.full_like(score, -math.inf))
    peak = score.argmax(-1).to(torch.float64)  # [B]
    k = torch.arange(cross.shape[-1], dtype=torch.float64, device=cross.device)
    # residual phase after removing the integer shift: -2 pi k d / W, fitted through the origin
    residual = torch.angle(cross * torch.exp(2j * math.pi * k * peak[:, None] / width))
    n_low = max(2, round(low_band * width))
    weight = cross.abs()[:, 1:n_low] * k[1:n_low]
    slope = (weight * residual[:, 1:n_low]).sum(-1) / (weight * k[1:n_low]).sum(-1).clamp_min(1e-30)
    # a fraction of a column; no more than one (the peak of a window need not be the strongest one, whose
    # leftover phases would otherwise drag the shift out of the window)
    shift = peak - (slope * width / (2 * math.pi)).clamp(-1.0, 1.0)
    return torch.remainder(shift + width / 2, width) - width / 2


def compass_yaw(
    a: Tensor,
    b: Tensor,
    mask: Tensor | None = None,
    near: Tensor | None = None,
    within: float | Tensor | None = None,
) -> Tensor:
    """The yaw (radians) between the cameras of two full panoramas ``a`` and ``b``.

    Camera points of ``b`` are ``yaw_matrix(yaw) @`` those of ``a`` (as for a panorama rolled by
    :func:`cylsfm.geometry.roll_columns`, see :func:`cylsfm.geometry.roll_angle`), so the relative pose
    ``T_{a->b}`` (``p_b = T p_a``) has the rotation ``yaw_matrix(yaw)`` (the camera itself turned by
    ``-yaw``: a positive yaw moves the scene's azimuths up, :func:`cylsfm.geometry.roll_angle`).

    Args:
        a: panoramas ``[B, C, H, W]``, full 360° width.
        b: the same cameras after the motion, same shape.
        mask: as for :func:`column_shift`.
        near, within: ``[B]`` yaws (radians) and the largest distance from them (radians, a number or
            ``[B]``): only yaws that close are considered (see :func:`column_shift`); ``None``: any yaw.

    Returns:
        ``[B]`` yaws in radians (float64), in ``[-pi, pi)``.
    """
    per = a.shape[-1] / (2 * math.pi)  # columns per radian
    if near is not None:
        within = None if within is None else torch.as_tensor(within, dtype=torch.float64) * per
        near = near.to(torch.float64) * per
    return column_shift(a, b, mask=mask, near=near, within=within) / per


def compass_yaws(target: Tensor, sources: Tensor, mask: Tensor | None = None) -> Tensor:
    """The yaw (radians) from each target to each of its sources: :func:`compass_yaw` of every pair, with
    each target's spectrum computed once.

    Args:
        target: panoramas ``[B, C, H, W]``, full 360° width.
        sources: ``[B, S, C, H, W]``.
        mask: ``[1, 1, H, W]`` or ``None`` (as for :func:`column_shift`).

    Returns:
        ``[B, S]`` yaws (float64), equal to ``compass_yaw(target[b], sources[b, s])``.

    >>> t = torch.rand(2, 3, 8, 64)
    >>> y = compass_yaws(t, torch.stack((torch.roll(t, 3, -1), t), 1))
    >>> bool(torch.allclose(y, torch.tensor([[3.0, 0.0]] * 2, dtype=torch.float64) * 2 * math.pi / 64))
    True
    """
    check_shape(target, "B,C,H,W", "target")
    if sources.dim() != 5 or sources.shape[0] != target.shape[0] or sources.shape[2:] != target.shape[1:]:
        raise ShapeError(
            f"compass_yaws: sources {tuple(sources.shape)} do not fit target {tuple(target.shape)}"
        )
    if mask is not None and (mask.dim() != 4 or mask.shape[0] != 1 or mask.shape[-2:] != target.shape[-2:]):
        raise ShapeError(f"compass_yaws: mask {tuple(mask.shape)} must be [1,1,H,W] of the images")
    b, s, width = sources.shape[0], sources.shape[1], target.shape[-1]
    spec_t = _spectrum(target, mask)  # [B, CH, F]
    spec_s = _spectrum(sources.flatten(0, 1), mask).view(b, s, *spec_t.shape[1:])
    cross = (spec_t.conj()[:, None] * spec_s).sum(2).flatten(0, 1)  # [B*S, F]
    return (_shift_of(cross, width) / (width / (2 * math.pi))).view(b, s)


def window_yaws(frames: Tensor, k: int) -> Tensor:
    """:func:`compass_yaws` of every window of ``2k + 1`` consecutive frames (the middle frame the target,
    the others its sources in time order), each frame's spectrum computed once.

    Args:
        frames: panoramas ``[N, C, H, W]`` in time order, full 360° width, ``N >= 2k + 1``.
        k: frames either side of a window's target.

    Returns:
        ``[N - 2k, 2k]`` yaws (float64) from each window's target to its sources, equal to
        ``compass_yaws(frames[k:N-k], sources)`` of those windows.

    >>> t = torch.rand(1, 3, 8, 64)
    >>> y = window_yaws(torch.cat((t, torch.roll(t, 2, -1), torch.roll(t, 5, -1))), 1)
    >>> bool(torch.allclose(y, torch.tensor([[-2.0, 3.0]], dtype=torch.float64) * 2 * math.pi / 64))
    True
    """
    check_shape(frames, "N,C,H,W", "frames")
    n, width = frames.shape[0], frames.shape[-1]
    if k < 1 or n < 2 * k + 1:
        raise ShapeError(f"window_yaws: {n} frames hold no window of {2 * k + 1}")
    m = n - 2 * k
    spec = _spectrum(frames)  # [N, CH, F]
    sources = torch.stack([spec[k + o : k + o + m] for o in range(-k, k + 1) if o], 1)  # [m, 2k, CH, F]
    cross = (spec[k : k + m].conj()[:, None] * sources).sum(2).flatten(0, 1)
    return (_shift_of(cross, width) / (width / (2 * math.pi))).view(m, 2 * k)
