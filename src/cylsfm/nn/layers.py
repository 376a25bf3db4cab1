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

import torch
from torch import nn

from ..errors import InputError
from ..geometry.seam import resize_image
from .packed import PackedWeights
from .padding import circular_pad, pad_cat, relu_pad
from .small_maps import conv2d_rows_padded, conv_transpose2d_small

__all__ = [
    "MIN_HEIGHT",
    "MIN_WIDTH",
    "TOTAL_STRIDE",
    "WrapConv2d",
    "WrapConvTranspose2d",
    "check_input_size",
    "crop_like",
    "init_weights",
    "pad_cat",
    "relu_pad",
    "set_wrap",
    "wrap_upsample2x",
]


#: Total horizontal stride of the 7 stride-2 encoder stages (2**7).  With wrap-around the panorama
#: width must be a multiple of it so that every feature map is an exact circular sub-sampling.
TOTAL_STRIDE = 128
#: Minimum image height (rows) accepted by the networks.
MIN_HEIGHT = 32
#: Minimum image width (columns) accepted by the networks when wrap-around is off.
MIN_WIDTH = 32


def check_input_size(width: int, height: int, wrap: bool) -> None:
    """Validate an input image size for :class:`DispNet` / :class:`~cylsfm.nn.PoseExpNet`.

    Args:
        width: image width in pixels (azimuth columns).
        height: image height in pixels (rows).
        wrap: whether horizontal wrap-around (full 360° panorama) is on.

    Raises:
        InputError: if ``height < 32``; with ``wrap`` if ``width`` is not a positive multiple of 128
            (the message names the nearest valid widths); without ``wrap`` if ``width < 32``.
    """
    width, height = int(width), int(height)
    if height < MIN_HEIGHT:
        raise InputError(f"input height {height} is too small: the networks need height >= {MIN_HEIGHT}")
    if wrap:
        if width <= 0 or width % TOTAL_STRIDE != 0:
            lower = (width // TOTAL_STRIDE) * TOTAL_STRIDE
            upper = lower + TOTAL_STRIDE
            nearest = f"{lower} or {upper}" if lower > 0 else f"{upper}"
            raise InputError(
                f"input width {width} is not a multiple of {TOTAL_STRIDE} (the total encoder stride 2^7): "
                f"with wrap=True the panorama width must be a multiple of {TOTAL_STRIDE} so the wrap-around "
                f"is exact at every scale; resize it to e.g. {nearest}, or use wrap=False for images that "
                f"are not full 360° panoramas"
            )
    elif width < MIN_WIDTH:
        raise InputError(f"input width {width} is too small: the networks need width >= {MIN_WIDTH}")


def init_weights(module: nn.Module) -> None:
    """Xavier-uniform init of every (transposed) convolution weight in ``module``; zero biases."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


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
        #: the weight laid out for oneDNN at inference (:mod:`cylsfm.nn.packed`; never saved)
        self.packed_weights = PackedWeights()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Convolve ``x`` ``[B, in_channels, H, W]`` -> ``[B, out_channels, H_out, W_out]``."""
        if not self.wrap or self.pad == 0:
            out = self.packed_weights.conv2d(x, self.weight, self.bias, self.stride, self.padding)
            return super().forward(x) if out is None else out
        return self.forward_padded(circular_pad(x, self.pad, self.pad))

    def forward_padded(self, x: torch.Tensor) -> torch.Tensor:
        """Convolve an input already padded circularly by ``self.pad`` columns (see :func:`pad_cat`)."""
        return conv2d_rows_padded(x, self.weight, self.bias, self.stride, self.pad, self.packed_weights)

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
        #: the weight laid out for oneDNN at inference (:mod:`cylsfm.nn.packed`; never saved)
        self.packed_weights = PackedWeights()

    def _up(self, x: torch.Tensor) -> torch.Tensor:
        return conv_transpose2d_small(
            x, self.weight, self.bias, self.stride, self.padding, self.output_padding, self.packed_weights
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        """Up-convolve ``x`` ``[B, in_channels, H, W]`` -> ``[B, out_channels, s*H, s*W]``."""
        if not self.wrap:
            out = self.packed_weights.conv_transpose2d(
                x, self.weight, self.bias, self.stride, self.padding, self.output_padding
            )
            return super().forward(x) if out is None else out
        s = self.stride[1]
        width = x.shape[-1]
        xp = circular_pad(x, self.wrap_left, self.wrap_right)
        out = self._up(xp)
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
        return self._up(xp), self.stride[1] * pad

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
