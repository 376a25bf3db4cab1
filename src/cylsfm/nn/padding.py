"""The networks' padding kernels: circular padding with lean backward passes, fused with a concatenation
or a ReLU, so that the wrap-aware layers keep their feature maps padded at no extra pass over memory.

The meaning of the seam (which column neighbours which) is :mod:`cylsfm.geometry.seam`'s; the functions
here compute the same values as its :func:`~cylsfm.geometry.seam.circular_pad` (tested), with custom
autograd functions whose backward passes copy once instead of adding zero-filled slices. Exporters and
compilers trace standard operators instead (:func:`standard_ops`). With ``circular=False`` the pads are
zeros: the same layers then compute the ordinary convolutions of a bounded image.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
import torch.nn.functional as F

from ..errors import InputError
from ..geometry import seam
from ..geometry.seam import memory_format_of

__all__ = ["circular_pad", "pad_cat", "relu_pad", "standard_ops", "tracing"]


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


def tracing() -> bool:
    """Whether an exporter (inside :func:`standard_ops`) or a compiler is tracing the networks now."""
    return _STANDARD_OPS or torch.compiler.is_compiling()


def circular_pad(x: torch.Tensor, left: int, right: int) -> torch.Tensor:
    """``x [..., W]`` padded circularly by ``left`` / ``right`` columns: the values (arguments, shapes and
    memory format) of :func:`cylsfm.geometry.seam.circular_pad`, with a lean backward pass where neither
    pad exceeds ``W``."""
    w = x.shape[-1]
    if (left or right) and left <= w and right <= w and not tracing():
        return _CircularPadWidth.apply(x, left, right)
    return seam.circular_pad(x, left, right)


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
    circular: bool = True,
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
        circular: pad circularly; ``False``: with zeros (a bounded image).

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
    if not circular:
        cat = torch.cat([p[..., s : s + width] for p, s in zip(parts, starts_t, strict=True)], 1)
        return F.pad(cat, (pad, pad)).contiguous(memory_format=fmt)
    if tracing():
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


def relu_pad(
    y: torch.Tensor, pad: int, window: tuple[int, int, int] | None = None, circular: bool = True
) -> torch.Tensor:
    """``relu`` of ``y`` (or of a window of it), padded circularly by ``pad`` columns, in one copy.

    Replaces the in-place ReLU after a convolution when the next convolution wraps: the padding then
    costs no extra pass over the feature map (see :meth:`WrapConv2d.forward_padded`).

    Args:
        y: ``[B, C, H, W]``, e.g. a convolution's output.
        pad: columns copied circularly onto each side, ``>= 0``.
        window: ``(height, start, width)``: use only rows ``[0, height)`` and columns
            ``[start, start + width)`` of ``y`` (an up-convolution's output cropped to its skip
            connection); default all of ``y``.
        circular: pad circularly; ``False``: with zeros (a bounded image).

    Returns:
        ``[B, C, height, width + 2 pad]`` in ``y``'s memory format.  The gradient has ``y``'s full shape
        (zero outside the window).
    """
    height, start, width = window if window is not None else (y.shape[-2], 0, y.shape[-1])
    if not circular:
        return F.pad(torch.relu(y[..., :height, start : start + width]), (pad, pad))
    if pad > width or tracing():  # tiny feature maps wrap around more than once
        return circular_pad(torch.relu(y[..., :height, start : start + width]), pad, pad)
    return _ReLUPad.apply(y, int(pad), int(height), int(start), int(width))
