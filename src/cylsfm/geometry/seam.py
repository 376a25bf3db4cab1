"""The seam of a full 360-degree panorama: every circular pad, roll, difference and resize in one place.

The width axis of a full cylindrical panorama is periodic: column ``W`` is column ``0``. Everything in
cylsfm that looks across the left/right border of an image goes through this module:

* :func:`circular_pad` pads the width circularly (the bilinear sampler; the networks' layers use the same
  padding with lean backward passes, fused with a concatenation or a ReLU, from :mod:`cylsfm.nn.padding`);
* :func:`pad_for_window` pads for 3x3 windows (SSIM): circular horizontally, reflected vertically;
* :func:`column_difference` is the forward difference along the width (smoothness losses);
* :func:`resize_image` is the bilinear resize that blends across the seam (network scales, evaluation);
* :func:`roll_columns` turns a panorama, its depth or its mask about the vertical axis (augmentation,
  yaw-rolled evaluation), and :func:`roll_angle` / :func:`roll_pose` turn the poses with it.

Every function takes a ``wrap`` switch or is only called when the camera wraps; with wrap off the
operations are the ordinary ones of a bounded image. All tensors are ``[..., H, W]`` unless stated.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError
from .pose import invert, yaw_transform

__all__ = [
    "circular_pad",
    "column_difference",
    "memory_format_of",
    "pad_for_window",
    "resize_image",
    "roll_angle",
    "roll_columns",
    "roll_pose",
]


def memory_format_of(x: torch.Tensor) -> torch.memory_format:
    """The memory format ``x`` (4-D, possibly a view such as a column window) is laid out in.

    ``torch.channels_last`` when the channel stride is smaller than the width stride (channels innermost),
    else ``torch.contiguous_format``.  Judged from the strides, not from contiguity: a column window of a
    channels-last tensor is contiguous in neither format but must be copied as channels-last (a copy
    between the two layouts is a transpose, many times slower than a plain copy).
    """
    if x.dim() == 4 and x.shape[1] > 1 and x.stride(1) < x.stride(3):
        return torch.channels_last
    return torch.contiguous_format


def circular_pad(x: torch.Tensor, left: int, right: int) -> torch.Tensor:
    """Pad the last (width) dimension of ``x`` circularly by ``left`` / ``right`` columns.

    Args:
        x: tensor ``[..., W]`` with ``W >= 1``.
        left: number of columns taken from the right edge and prepended (``>= 0``).
        right: number of columns taken from the left edge and appended (``>= 0``).

    Returns:
        Tensor ``[..., left + W + right]`` with the same memory format as ``x``.  Unlike
        ``F.pad(..., mode="circular")`` the padding may exceed ``W`` (the panorama then wraps around
        more than once), and channels-last inputs stay channels-last.  (The networks' layers use
        :func:`cylsfm.nn.padding.circular_pad`, the same values with a leaner backward pass.)

    Example:
        >>> circular_pad(torch.arange(4.0), 1, 2).tolist()
        [3.0, 0.0, 1.0, 2.0, 3.0, 0.0, 1.0]
    """
    w = x.shape[-1]
    if left == 0 and right == 0:
        return x
    n_left, n_right = math.ceil(left / w), math.ceil(right / w)
    if n_left <= 1 and n_right <= 1:
        return torch.cat([x[..., w - left :], x, x[..., :right]], dim=-1)
    # very narrow maps (e.g. width 1 at the deepest level): tile then slice
    tiled = torch.cat([x] * (n_left + 1 + n_right), dim=-1)
    start = n_left * w - left
    out = tiled[..., start : start + left + w + right]
    return out.contiguous(memory_format=memory_format_of(x))


def pad_for_window(x: Tensor, wrap: bool) -> Tensor:
    """Pad ``[B,C,H,W]`` by one pixel on every side for a 3x3 window -> ``[B,C,H+2,W+2]``.

    Circular horizontally with ``wrap``, reflected otherwise; always reflected vertically.
    """
    if wrap:
        return F.pad(circular_pad(x, 1, 1), (0, 0, 1, 1), mode="reflect")
    return F.pad(x, (1, 1, 1, 1), mode="reflect")


def column_difference(t: Tensor, wrap: bool) -> Tensor:
    """Forward difference along the width: ``t[..., j+1] - t[..., j]``.

    ``[..., H, W] -> [..., H, W]`` with ``wrap`` (the last column differences across the seam with column
    0), ``[..., H, W-1]`` without. Both agree on their common columns ``0 .. W-2``.

    >>> column_difference(torch.tensor([[1.0, 2.0, 4.0]]), wrap=True)
    tensor([[ 1.,  2., -3.]])
    >>> column_difference(torch.tensor([[1.0, 2.0, 4.0]]), wrap=False)
    tensor([[1., 2.]])
    """
    if wrap:
        return torch.roll(t, -1, dims=-1) - t
    return t[..., 1:] - t[..., :-1]


def resize_image(x: Tensor, size: tuple[int, int], wrap: bool) -> Tensor:
    """Bilinear resize of ``x [B,C,h,w]`` to ``size = (H, W)`` (``align_corners=False``).

    With ``wrap`` the width is periodic and the interpolation blends across the seam: one column of
    circular padding on each side is resized with the image and cropped away afterwards. This is exact
    when ``W`` is an integer multiple of ``w`` (the up-sampling between network scales); other widths
    are refused with ``wrap``.

    >>> x = torch.tensor([[[[0.0, 1.0]]]])
    >>> resize_image(x, (1, 4), wrap=True)  # the outer columns blend with the opposite edge
    tensor([[[[0.2500, 0.2500, 0.7500, 0.7500]]]])
    >>> resize_image(x, (1, 4), wrap=False)
    tensor([[[[0.0000, 0.2500, 0.7500, 1.0000]]]])
    """
    h_out, w_out = size
    if tuple(x.shape[-2:]) == (h_out, w_out):
        return x
    if not wrap:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    w = x.shape[-1]
    if w_out % w:
        raise InputError(f"a wrapping resize needs an integer width factor, got {w} -> {w_out} columns")
    factor = w_out // w
    # A plain autograd concatenation (not circular_pad's lean backward): these maps are small, and it
    # keeps the order in which gradients are summed, hence the training numbers, as they always were.
    padded = torch.cat((x[..., -1:], x, x[..., :1]), -1)
    big = F.interpolate(padded, size=(h_out, (w + 2) * factor), mode="bilinear", align_corners=False)
    return big[..., factor : factor + w_out]


ArrayT = TypeVar("ArrayT", Tensor, np.ndarray)


def roll_columns(x: ArrayT, k: int, axis: int = -1) -> ArrayT:
    """Turn a full panorama about its vertical axis: roll ``x`` by ``k`` columns along ``axis``.

    Column ``j`` moves to column ``(j + k) mod W``: azimuths increase by ``2 pi k / W``
    (see :func:`roll_angle`). Works on tensors and NumPy arrays alike; returns ``x`` itself (no copy)
    when ``k == 0``. Images ``[..., H, W]`` use ``axis=-1``; NumPy frames ``[H, W, 3]`` ``axis=1``.

    >>> roll_columns(np.arange(4), 1)
    array([3, 0, 1, 2])
    """
    if not k:
        return x
    if isinstance(x, Tensor):
        return torch.roll(x, int(k), dims=axis)
    return np.roll(x, int(k), axis=axis)


def roll_angle(k: float, width: int) -> float:
    """The azimuth increase (radians) of a panorama rolled by ``k`` of its ``width`` columns: ``2 pi k / W``.

    Camera points of the rolled panorama are ``yaw_matrix(roll_angle(k, W)) @`` those of the original,
    so a relative pose ``T`` becomes ``Y T Y^-1`` and a camera-to-world pose ``c2w`` becomes ``c2w Y^-1``
    (see :func:`roll_pose`).

    >>> round(roll_angle(128, 512), 6) == round(math.pi / 2, 6)
    True
    """
    return 2.0 * math.pi * float(k) / width


def roll_pose(pose: ArrayT, k: float, width: int, camera_to_world: bool = False) -> ArrayT:
    """Turn poses ``[..., 4, 4]`` with panoramas rolled by ``k`` columns (tensors or NumPy arrays).

    Args:
        pose: relative transforms ``T_tgt_to_src`` (both cameras turned: ``Y T Y^-1``), or with
            ``camera_to_world`` camera-to-world poses (``c2w Y^-1``).
        k: the roll in columns, as given to :func:`roll_columns`.
        width: the panorama's width in columns.
    """
    yaw = yaw_transform(roll_angle(k, width), pose)
    if camera_to_world:
        return pose @ invert(yaw)
    return yaw @ pose @ invert(yaw)
