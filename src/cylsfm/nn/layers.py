"""Wrap-aware convolution layers for 360° cylindrical panoramas.

All tensors are image-like, shaped ``[B, C, H, W]``: ``H`` is the vertical (image row) axis and ``W``
is azimuth.  For a full 360° panorama the width axis is periodic, so the layers here can treat it
as a circle ("wrap" on): horizontal padding copies columns from the opposite edge instead of
inserting zeros, which makes every layer equivariant to horizontal rolls (yaw rotations of the
camera about its vertical y axis) by a whole number of output columns.  Vertical padding is always
zero padding.  With wrap off each layer behaves exactly like its ordinary ``torch.nn`` counterpart,
which is what partial panoramas and perspective images need.

The switch is a plain boolean attribute ``wrap`` on every wrap-aware module; the weights are the same
either way, so a trained network can be evaluated with or without wrap-around (see :func:`set_wrap`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..geometry import resize_image

__all__ = [
    "WrapConv2d",
    "WrapConvTranspose2d",
    "crop_like",
    "pad_cat",
    "relu_pad",
    "set_wrap",
    "wrap_upsample2x",
]


def _memory_format_of(x: torch.Tensor) -> torch.memory_format:
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
        gx = grad[..., left : left + w].clone(memory_format=_memory_format_of(grad))
        if left:
            gx[..., w - left :] += grad[..., :left]
        if right:
            gx[..., :right] += grad[..., left + w :]
        return gx, None, None


def _circular_pad_width(x: torch.Tensor, left: int, right: int) -> torch.Tensor:
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
        return _CircularPadWidth.apply(x, left, right)
    # Very narrow feature maps (e.g. width 1 at the deepest level): tile then slice.
    n_left = math.ceil(left / w)
    n_right = math.ceil(right / w)
    tiled = torch.cat([x] * (n_left + 1 + n_right), dim=-1)
    start = n_left * w - left
    out = tiled[..., start : start + left + w + right]
    return out.contiguous(memory_format=_memory_format_of(x))


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
        ctx.meta = (pad, w, channels, starts, [p.shape for p in parts], [_memory_format_of(p) for p in parts])
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
        raise ValueError(f"pad_cat: padding {pad} must be in [0, width={width}]")
    fmt = memory_format if memory_format is not None else _memory_format_of(parts[0])
    return _PadCat.apply(pad, int(width), starts_t, fmt, *parts)


class _ReLUPad(torch.autograd.Function):
    """ReLU of a window of a tensor, padded circularly, in one copy (and one pass back)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, y: torch.Tensor, pad: int, height: int, start: int, width: int
    ) -> torch.Tensor:
        b, c = y.shape[:2]
        fmt = _memory_format_of(y)
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
    if pad > width:  # tiny feature maps: wrap around more than once
        return _circular_pad_width(torch.relu(y[..., :height, start : start + width]), pad, pad)
    return _ReLUPad.apply(y, int(pad), int(height), int(start), int(width))


class WrapConv2d(nn.Conv2d):
    """2-D convolution with "same"-style padding that wraps around horizontally.

    The padding is ``p = (kernel_size - 1) // 2`` on every side.  With ``wrap=True`` the ``p`` columns
    on each side are copied circularly from the opposite edge (one ``torch.cat`` copy) and the
    vertical padding is ordinary zero padding done by the convolution itself.  With ``wrap=False``
    this is exactly ``nn.Conv2d(..., padding=p)``.

    Shapes:
        input ``[B, in_channels, H, W]`` -> output ``[B, out_channels, H_out, W_out]`` with
        ``H_out = floor((H + 2p - k) / stride) + 1`` (``ceil(H / stride)`` for odd ``k``), and ``W_out``
        likewise.  With wrap on, rolling the input by ``stride * m`` columns rolls the output by ``m``
        columns exactly when ``W`` is a multiple of ``stride``.

    Channels-last inputs give channels-last outputs.

    Args:
        in_channels: input channels.
        out_channels: output channels.
        kernel_size: square kernel size ``k`` (odd sizes give symmetric "same" padding).
        stride: stride in both directions.
        bias: whether to learn an additive bias.
        wrap: initial value of the ``wrap`` switch (may be changed later, see :func:`set_wrap`).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int = 1,
        bias: bool = True,
        wrap: bool = True,
    ) -> None:
        pad = (kernel_size - 1) // 2
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=pad, bias=bias)
        self.wrap = wrap
        self.pad = pad

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Convolve ``x`` ``[B, in_channels, H, W]`` -> ``[B, out_channels, H_out, W_out]``."""
        if not self.wrap or self.pad == 0:
            return super().forward(x)
        x = _circular_pad_width(x, self.pad, self.pad)
        return F.conv2d(x, self.weight, self.bias, self.stride, (self.pad, 0))

    def forward_padded(self, x: torch.Tensor) -> torch.Tensor:
        """Convolve an input already padded circularly by ``self.pad`` columns (see :func:`pad_cat`)."""
        return F.conv2d(x, self.weight, self.bias, self.stride, (self.pad, 0))

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, wrap={self.wrap}"


class WrapConvTranspose2d(nn.ConvTranspose2d):
    """Transposed ("up-") convolution whose width axis is treated as a circle when ``wrap`` is on.

    Defaults give the SfMLearner up-convolution: kernel 3, stride 2, padding 1, output padding 1, so
    an input ``[B, C, H, W]`` produces exactly ``[B, out_channels, 2H, 2W]``.  In general the padding is
    ``p = (k - 1) // 2`` and the output padding ``s + 2p - k`` is chosen so the output is
    ``[B, out_channels, s*H, s*W]``.

    With ``wrap=True`` the horizontal direction is the exact circular transposed convolution, i.e.
    the adjoint of the circular strided convolution of :class:`WrapConv2d`: output column ``o``
    receives input column ``i`` through kernel tap ``kk`` when ``o ≡ s*i + kk - p (mod s*W)``.  It is
    computed by padding the input circularly by the few columns that reach into ``[0, s*W)`` across
    the seam (``l = (k - 1 - p) // s`` on the left, ``r = (s - 1 + p) // s`` on the right: 0 and 1 for the
    SfMLearner up-convolution), running the ordinary transposed convolution on it and keeping output
    columns ``[s*l, s*l + s*W)``.  Rolling the input by ``m`` columns then rolls the output by ``s*m``
    columns.  With ``wrap=False`` this is exactly ``nn.ConvTranspose2d``.

    With wrap the output is a view (a column window) of the convolution's result: the consumers (a
    concatenation with a skip connection, a convolution) copy it anyway.

    Args:
        in_channels: input channels.
        out_channels: output channels.
        kernel_size: square kernel size ``k``.
        stride: up-sampling factor ``s`` in both directions.
        bias: whether to learn an additive bias.
        wrap: initial value of the ``wrap`` switch (may be changed later, see :func:`set_wrap`).

    Raises:
        ValueError: if no valid output padding gives an output of exactly ``s`` times the input size.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        stride: int = 2,
        bias: bool = True,
        wrap: bool = True,
    ) -> None:
        pad = (kernel_size - 1) // 2
        out_pad = stride + 2 * pad - kernel_size
        if not 0 <= out_pad < stride:
            raise ValueError(
                f"WrapConvTranspose2d: kernel_size={kernel_size}, stride={stride} cannot give an output of "
                f"exactly stride * input size (would need output_padding={out_pad}, valid range [0, {stride}))"
            )
        super().__init__(
            in_channels,
            out_channels,
            kernel_size,
            stride=stride,
            padding=pad,
            output_padding=out_pad,
            bias=bias,
        )
        self.wrap = wrap
        self.wrap_left = max(0, (kernel_size - 1 - pad) // stride)
        self.wrap_right = (stride - 1 + pad) // stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        """Up-convolve ``x`` ``[B, in_channels, H, W]`` -> ``[B, out_channels, s*H, s*W]``."""
        if not self.wrap:
            return super().forward(x)
        s = self.stride[1]
        width = x.shape[-1]
        out = super().forward(_circular_pad_width(x, self.wrap_left, self.wrap_right))
        start = s * self.wrap_left
        return out[..., start : start + s * width]

    def forward_padded(self, xp: torch.Tensor, pad: int) -> tuple[torch.Tensor, int]:
        """Up-convolve an input already padded circularly by ``pad`` columns on each side.

        Args:
            xp: ``[B, in_channels, H, W + 2 pad]`` with ``pad >= max(wrap_left, wrap_right)`` (1 for
                the SfMLearner up-convolution), e.g. from :func:`relu_pad`.
            pad: that padding.

        Returns:
            ``(out, start)``: the convolution's whole output ``[B, out_channels, s*H, s*(W + 2 pad)]``
            and the first of its ``s*W`` columns that form the circular up-convolution of the centre
            (equal to :meth:`forward` of the unpadded input); crop with ``out[..., start:start + s*W]``
            or pass the window to :func:`relu_pad`.
        """
        if pad < self.wrap_left or pad < self.wrap_right:
            raise ValueError(
                f"forward_padded: padding {pad} is less than the {max(self.wrap_left, self.wrap_right)} "
                "columns the up-convolution needs"
            )
        out = F.conv_transpose2d(
            xp,
            self.weight,
            self.bias,
            self.stride,
            self.padding,
            self.output_padding,
            self.groups,
            self.dilation,
        )
        return out, self.stride[1] * pad

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, wrap={self.wrap}"


def wrap_upsample2x(x: torch.Tensor, wrap: bool) -> torch.Tensor:
    """Bilinear x2 up-sampling (``align_corners=False``), blending across the seam when ``wrap``.

    With ``wrap`` the input is padded circularly by one column on each side, up-sampled to
    ``[2H, 2(W + 2)]`` and cropped by two columns on each side.  This is exactly bilinear
    interpolation on a periodic width axis: output column ``o`` samples input coordinate
    ``(o + 0.5) / 2 - 0.5``, which in padded coordinates is shifted by one and never needs
    edge clamping.  Vertically (and horizontally when ``wrap`` is False) edges are clamped as in
    ``F.interpolate``.

    Args:
        x: tensor ``[B, C, H, W]`` (any units; e.g. disparity in 1/depth units).
        wrap: treat the width axis as periodic.

    Returns:
        Tensor ``[B, C, 2H, 2W]``.
    """
    return resize_image(x, (2 * x.shape[-2], 2 * x.shape[-1]), wrap)


def crop_like(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Crop ``x`` ``[B, C, H, W]`` to the height and width of ``ref`` ``[B', C', H', W']`` (top-left corner).

    Used, as in SfMLearner, where an up-convolution output (``2 * ceil(H / 2)`` rows) is one row or
    column larger than the matching skip connection.  Returns a view ``[B, C, H', W']``.

    Raises:
        ValueError: if ``x`` is smaller than ``ref`` in either spatial dimension.
    """
    h, w = ref.shape[-2], ref.shape[-1]
    if x.shape[-2] < h or x.shape[-1] < w:
        raise ValueError(f"crop_like: cannot crop {tuple(x.shape)} to spatial size ({h}, {w})")
    return x[..., :h, :w]


def set_wrap(module: nn.Module, wrap: bool) -> None:
    """Set the ``wrap`` switch of ``module`` and of all its submodules that have one.

    A module is wrap-aware if it has a boolean attribute ``wrap`` (all layers in this file, and
    :class:`~cylsfm.nn.DispNet` / :class:`~cylsfm.nn.PoseExpNet` themselves).  Weights are unchanged.
    """
    for m in module.modules():
        if isinstance(getattr(m, "wrap", None), bool):
            m.wrap = bool(wrap)
