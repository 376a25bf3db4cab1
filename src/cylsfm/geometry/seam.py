"""The seam of a full 360-degree panorama: every circular pad, roll, difference and resize in one place.

The width axis of a full cylindrical panorama is periodic: column ``W`` is column ``0``. Everything in
cylsfm that looks across the left/right border of an image goes through this module:

* :func:`circular_pad` pads the width circularly (the wrap-aware convolutions, the bilinear sampler);
  :func:`pad_cat` and :func:`relu_pad` are the same padding fused with a channel concatenation or a ReLU,
  so that the networks keep their feature maps padded at no extra pass over memory;
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
from collections.abc import Iterator
from contextlib import contextmanager
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
    "pad_cat",
    "pad_for_window",
    "relu_pad",
    "resize_image",
    "roll_angle",
    "roll_columns",
    "roll_pose",
    "standard_ops",
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


class _CircularPadWidth(torch.autograd.Function):
    """Circular padding of the width with a lean backward pass.

    Forward is one copy (``torch.cat`` of the edge columns and the input). Autograd's own backward of that
    ``cat`` would materialise a zero-filled full-size gradient for every edge slice and add them up; here
    the gradient is the centre of the incoming gradient plus the edge gradients added into the opposite
    columns: one copy.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, left: int, right: int) -> torch.Tensor:  # type: ignore[override]
        w = x.shape[-1]
        ctx.pads = (left, right, w)
        pieces = [x[..., w - left :]] if left else []
        pieces.append(x)
        if right:
            pieces.append(x[..., :right])
        return torch.cat(pieces, dim=-1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        left, right, w = ctx.pads
        gx = grad[..., left : left + w].clone(memory_format=memory_format_of(grad))
        if left:
            gx[..., w - left :] += grad[..., :left]
        if right:
            gx[..., :right] += grad[..., left + w :]
        return gx, None, None


_STANDARD_OPS = False


@contextmanager
def standard_ops() -> Iterator[None]:
    """Within this block the padding functions use only standard tensor operations (slicing, ``cat``,
    ``relu``) instead of their fused autograd functions: the same values, in a form that exporters
    (ONNX, ``torch.export``) and compilers can trace. Used for inference exports; training keeps the
    fused forms, whose backward passes are leaner.
    """
    global _STANDARD_OPS
    previous, _STANDARD_OPS = _STANDARD_OPS, True
    try:
        yield
    finally:
        _STANDARD_OPS = previous


def _plain() -> bool:
    return _STANDARD_OPS or torch.compiler.is_compiling()


def circular_pad(x: torch.Tensor, left: int, right: int) -> torch.Tensor:
    """Pad the last (width) dimension of ``x`` circularly by ``left`` / ``right`` columns.

    Args:
        x: tensor ``[..., W]`` with ``W >= 1``.
        left: number of columns taken from the right edge and prepended (``>= 0``).
        right: number of columns taken from the left edge and appended (``>= 0``).

    Returns:
        Tensor ``[..., left + W + right]`` with the same memory format as ``x``.  Unlike
        ``F.pad(..., mode="circular")`` the padding may exceed ``W`` (the panorama then wraps around
        more than once), and channels-last inputs stay channels-last (``F.pad`` in circular mode
        returns a standard-contiguous tensor for a channels-last input).
    """
    w = x.shape[-1]
    if left == 0 and right == 0:
        return x
    if left <= w and right <= w:
        if _plain():
            return torch.cat([x[..., w - left :], x, x[..., :right]], dim=-1)
        return _CircularPadWidth.apply(x, left, right)
    # Very narrow feature maps (e.g. width 1 at the deepest level): tile then slice.
    n_left = math.ceil(left / w)
    n_right = math.ceil(right / w)
    tiled = torch.cat([x] * (n_left + 1 + n_right), dim=-1)
    start = n_left * w - left
    out = tiled[..., start : start + left + w + right]
    return out.contiguous(memory_format=memory_format_of(x))


def _zero_outside(g: torch.Tensor, height: int, start: int, width: int) -> None:
    """Zero ``g`` ``[..., H, W]`` outside rows ``[0, height)`` x columns ``[start, start + width)``."""
    if height < g.shape[-2]:
        g[..., height:, :].zero_()
    if start:
        g[..., :height, :start].zero_()
    if start + width < g.shape[-1]:
        g[..., :height, start + width :].zero_()


class _PadCat(torch.autograd.Function):
    """Channel concatenation of column windows and circular width padding in one copy (and one copy back)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, pad: int, width: int, starts: tuple[int, ...], fmt: torch.memory_format, *parts: torch.Tensor
    ) -> torch.Tensor:
        first = parts[0]
        b, h = first.shape[0], first.shape[-2]
        w = width
        channels = [p.shape[1] for p in parts]
        out = torch.empty(
            (b, sum(channels), h, w + 2 * pad), dtype=first.dtype, device=first.device, memory_format=fmt
        )
        c = 0
        for p, n, s in zip(parts, channels, starts, strict=True):
            win = p[..., s : s + w]
            out[:, c : c + n, :, pad : pad + w] = win
            if pad:
                out[:, c : c + n, :, :pad] = win[..., w - pad :]
                out[:, c : c + n, :, w + pad :] = win[..., :pad]
            c += n
        ctx.meta = (pad, w, channels, starts, [p.shape for p in parts], [memory_format_of(p) for p in parts])
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        pad, w, channels, starts, shapes, fmts = ctx.meta
        grads = []
        c = 0
        for n, s, shape, fmt in zip(channels, starts, shapes, fmts, strict=True):
            g = grad[:, c : c + n]
            gp = torch.empty(shape, dtype=grad.dtype, device=grad.device, memory_format=fmt)
            _zero_outside(gp, shape[-2], s, w)
            win = gp[..., s : s + w]
            win.copy_(g[..., pad : pad + w])
            if pad:
                win[..., w - pad :] += g[..., :pad]
                win[..., :pad] += g[..., w + pad :]
            grads.append(gp)
            c += n
        return (None, None, None, None, *grads)


def pad_cat(
    parts: list[torch.Tensor],
    pad: int,
    width: int | None = None,
    starts: list[int] | None = None,
    memory_format: torch.memory_format | None = None,
) -> torch.Tensor:
    """``torch.cat`` of column windows along channels, padded circularly by ``pad`` columns, in one copy.

    Part ``i`` contributes its columns ``[starts[i], starts[i] + width)``, e.g. the unpadded centre of a
    feature map kept padded for a convolution (``starts[i]`` = that padding).

    Args:
        parts: ``[B, C_i, H, W_i]`` tensors (views are fine), all of the same ``B`` and ``H``, with
            ``W_i >= starts[i] + width``.
        pad: circular padding on each side, ``0 <= pad <= width``.
        width: window width ``W``; default the first part's width minus its start.
        starts: first column of each part's window; default all 0.
        memory_format: layout of the result; default the first part's.

    Returns:
        ``[B, sum C_i, H, W + 2 pad]``, ready for :meth:`WrapConv2d.forward_padded`.  The gradient of
        each part has the part's full shape (zero outside its window).
    """
    starts_t = tuple(int(s) for s in starts) if starts is not None else (0,) * len(parts)
    if width is None:
        width = parts[0].shape[-1] - starts_t[0]
    if not 0 <= pad <= width:
        raise InputError(f"pad_cat: padding {pad} must be in [0, width={width}]")
    fmt = memory_format if memory_format is not None else memory_format_of(parts[0])
    if _plain():
        return circular_pad(
            torch.cat([p[..., s : s + width] for p, s in zip(parts, starts_t, strict=True)], 1), pad, pad
        )
    return _PadCat.apply(pad, int(width), starts_t, fmt, *parts)


class _ReLUPad(torch.autograd.Function):
    """ReLU of a window of a tensor, padded circularly, in one copy (and one pass back)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, y: torch.Tensor, pad: int, height: int, start: int, width: int
    ) -> torch.Tensor:
        b, c = y.shape[:2]
        fmt = memory_format_of(y)
        out = torch.empty((b, c, height, width + 2 * pad), dtype=y.dtype, device=y.device, memory_format=fmt)
        torch.clamp_min(y[..., :height, start : start + width], 0, out=out[..., pad : pad + width])
        if pad:
            out[..., :pad] = out[..., width : width + pad]
            out[..., width + pad :] = out[..., pad : 2 * pad]
        ctx.save_for_backward(out)
        ctx.meta = (pad, height, start, width, y.shape, fmt)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (out,) = ctx.saved_tensors
        pad, height, start, width, shape, fmt = ctx.meta
        threshold_backward = torch.ops.aten.threshold_backward
        gy = torch.empty(shape, dtype=grad.dtype, device=grad.device, memory_format=fmt)
        _zero_outside(gy, height, start, width)
        win = gy[..., :height, start : start + width]
        threshold_backward.grad_input(
            grad[..., pad : pad + width], out[..., pad : pad + width], 0, grad_input=win
        )
        if pad:
            win[..., width - pad :] += threshold_backward(grad[..., :pad], out[..., :pad], 0)
            win[..., :pad] += threshold_backward(grad[..., width + pad :], out[..., width + pad :], 0)
        return gy, None, None, None, None


def relu_pad(y: torch.Tensor, pad: int, window: tuple[int, int, int] | None = None) -> torch.Tensor:
    """``relu`` of ``y`` (or of a window of it), padded circularly by ``pad`` columns, in one copy.

    Replaces the in-place ReLU after a convolution when the next convolution wraps: the padding then
    costs no extra pass over the feature map (see :meth:`WrapConv2d.forward_padded`).

    Args:
        y: ``[B, C, H, W]``, e.g. a convolution's output.
        pad: columns copied circularly onto each side, ``>= 0``.
        window: ``(height, start, width)``: use only rows ``[0, height)`` and columns
            ``[start, start + width)`` of ``y`` (an up-convolution's output cropped to its skip
            connection); default all of ``y``.

    Returns:
        ``[B, C, height, width + 2 pad]`` in ``y``'s memory format.  The gradient has ``y``'s full shape
        (zero outside the window).
    """
    height, start, width = window if window is not None else (y.shape[-2], 0, y.shape[-1])
    if pad > width or _plain():  # tiny feature maps wrap around more than once
        return circular_pad(torch.relu(y[..., :height, start : start + width]), pad, pad)
    return _ReLUPad.apply(y, int(pad), int(height), int(start), int(width))


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
