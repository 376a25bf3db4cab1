"""SfMLearner's depth (disparity) network with horizontal wrap-around for cylindrical panoramas."""

from __future__ import annotations

import torch
from torch import nn

from ..errors import check_shape
from ..geometry.seam import memory_format_of
from .layers import (
    MIN_HEIGHT,
    MIN_WIDTH,
    TOTAL_STRIDE,
    WrapConv2d,
    WrapConvTranspose2d,
    check_input_size,
    crop_like,
    init_weights,
    wrap_upsample2x,
)
from .padding import pad_cat, relu_pad

__all__ = ["MIN_HEIGHT", "MIN_WIDTH", "TOTAL_STRIDE", "DispNet", "check_input_size"]  # size rules: .layers


class _ConvReLU(nn.Sequential):
    def __init__(self, cin: int, cout: int, k: int, stride: int, wrap: bool) -> None:
        super().__init__(WrapConv2d(cin, cout, k, stride=stride, wrap=wrap), nn.ReLU(inplace=True))


class _UpConvReLU(nn.Sequential):
    def __init__(self, cin: int, cout: int, wrap: bool) -> None:
        super().__init__(WrapConvTranspose2d(cin, cout, 3, stride=2, wrap=wrap), nn.ReLU(inplace=True))


class _DispHead(nn.Module):
    """3x3 conv to one channel followed by ``alpha * sigmoid + beta``."""

    def __init__(self, cin: int, alpha: float, beta: float, wrap: bool) -> None:
        super().__init__()
        self.conv = WrapConv2d(cin, 1, 3, wrap=wrap)
        self.alpha = alpha
        self.beta = beta

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.alpha * torch.sigmoid(self.conv(x)) + self.beta


class DispNet(nn.Module):
    """SfMLearner's encoder-decoder disparity network, wrap-around aware.

    Encoder: 7 stages with 32, 64, 128, 256, 512, 512, 512 channels and kernels 7, 5, 3, 3, 3, 3, 3; each
    stage is a stride-2 conv + ReLU followed by a stride-1 conv + ReLU.  Decoder: 7 up-convolutions
    (3x3, stride 2) + ReLU with 512, 512, 256, 128, 64, 32, 16 channels, each cropped to the matching
    skip connection and concatenated with it (and, at the three finest levels, with the x2 up-sampled
    coarser disparity), followed by a 3x3 conv + ReLU.  Disparities ``alpha * sigmoid(.) + beta`` are
    predicted at four scales.

    With ``wrap=True`` every convolution, up-convolution and disparity up-sampling treats the width
    (azimuth) axis as periodic, so for a full 360° panorama rolling the input by ``k`` columns
    (``k`` a multiple of 128) rolls the disparity at scale ``s`` by ``k / 2**s`` columns.  Use
    :func:`cylsfm.nn.set_wrap` to change ``wrap`` after construction (it flips every layer).

    Args:
        wrap: horizontal wrap-around (requires widths that are multiples of 128).
        alpha: disparity scale; disparities lie in ``(beta, alpha + beta)``.
        beta: minimum disparity.
    """

    enc_channels = (32, 64, 128, 256, 512, 512, 512)
    enc_kernels = (7, 5, 3, 3, 3, 3, 3)
    dec_channels = (512, 512, 256, 128, 64, 32, 16)

    def __init__(self, wrap: bool = True, alpha: float = 10.0, beta: float = 0.01) -> None:
        super().__init__()
        self.wrap = wrap
        self.alpha = alpha
        self.beta = beta

        enc_in = (3, *self.enc_channels[:-1])
        self.encoder = nn.ModuleList(
            nn.Sequential(_ConvReLU(cin, cout, k, 2, wrap), _ConvReLU(cout, cout, k, 1, wrap))
            for cin, cout, k in zip(enc_in, self.enc_channels, self.enc_kernels, strict=True)
        )

        # Decoder level 7 (coarsest) .. 1 (finest).  Skips: conv6 .. conv1 outputs, none at level 1.
        skips = (*self.enc_channels[:-1][::-1], 0)  # 512, 512, 256, 128, 64, 32, 0
        up_in = (self.enc_channels[-1], *self.dec_channels[:-1])
        self.upconvs = nn.ModuleList(
            _UpConvReLU(cin, cout, wrap) for cin, cout in zip(up_in, self.dec_channels, strict=True)
        )
        # The three finest levels also receive the up-sampled coarser disparity (one extra channel).
        extra = (0, 0, 0, 0, 1, 1, 1)
        self.iconvs = nn.ModuleList(
            _ConvReLU(cout + skip + e, cout, 3, 1, wrap)
            for cout, skip, e in zip(self.dec_channels, skips, extra, strict=True)
        )
        # Disparity heads on iconv4, iconv3, iconv2, iconv1 (decoder indices 3..6).
        self.disp_heads = nn.ModuleList(_DispHead(c, alpha, beta, wrap) for c in self.dec_channels[3:])

        init_weights(self)

    #: Validate an input size (:func:`cylsfm.nn.layers.check_input_size`; raises ``InputError``).
    check_input_size = staticmethod(check_input_size)

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        """Predict multi-scale disparity.

        Args:
            image: RGB image ``[B, 3, H, W]`` with values in ``[0, 1]``; it is normalised internally
                as ``(image - 0.5) / 0.5`` (in the network's dtype: a bf16 network reads fp32 images).  ``H >= 32``; with ``wrap`` ``W`` must be a multiple of 128,
                otherwise ``W >= 32``.

        Returns:
            Four disparity maps (inverse depth, in units of 1 / the depth scale), finest first:
            ``[B, 1, H_s, W_s]`` for ``s = 0..3`` where ``H_0 = H`` and ``H_s = ceil(H_{s-1} / 2)``
            (likewise for ``W``; exactly ``H / 2**s`` for multiples of 8).  Values lie in
            ``(beta, alpha + beta)``.

        Raises:
            ValueError: for a wrongly shaped input or an unsupported size (see :meth:`check_input_size`).
        """
        check_shape(image, "B,3,H,W", "image")
        check_input_size(image.shape[-1], image.shape[-2], self.wrap)
        if self.wrap:
            return self._forward_wrapped(image)
        return self._forward_modules(image)

    def _forward_modules(self, image: torch.Tensor) -> list[torch.Tensor]:
        """Layer by layer through the modules (each wrap-aware layer pads its own input)."""
        x = (image.to(self.encoder[0][0][0].weight.dtype) - 0.5) / 0.5
        feats = []
        for stage in self.encoder:
            x = stage(x)
            feats.append(x)
        # Skip for decoder level i (0 = coarsest): conv6 .. conv1 outputs, then the input image size.
        skip_feats: list[torch.Tensor | None] = [*feats[:-1][::-1], None]
        ref_sizes = [*feats[:-1][::-1], image]

        disps: list[torch.Tensor] = []
        x = feats[-1]
        for i, (upconv, iconv) in enumerate(zip(self.upconvs, self.iconvs, strict=True)):
            x = crop_like(upconv(x), ref_sizes[i])
            parts = [x]
            skip = skip_feats[i]
            if skip is not None:
                parts.append(skip)
            if disps:
                parts.append(crop_like(wrap_upsample2x(disps[-1], self.wrap), x))
            x = iconv(torch.cat(parts, dim=1))
            if i >= 3:
                disps.append(self.disp_heads[i - 3](x))
        return disps[::-1]

    def _forward_wrapped(self, image: torch.Tensor) -> list[torch.Tensor]:
        """The same computation with every feature map kept padded for the convolution that reads it.

        Each ReLU writes its output straight into a buffer padded circularly by the columns the next
        convolution needs (:func:`relu_pad`), and each decoder concatenation pads while it copies
        (:func:`pad_cat`), so the wrap-around costs no pass over the data beyond what the unwrapped
        network does.  Every feature is a pair (padded tensor, padding).
        """
        fmt = memory_format_of(self.encoder[0][0][0].weight)
        up_pad = max(max(u[0].wrap_left, u[0].wrap_right) for u in self.upconvs)
        first = self.encoder[0][0][0]
        xp = pad_cat([image.to(first.weight.dtype)], first.pad, memory_format=fmt).sub_(0.5).mul_(2.0)
        feats: list[tuple[torch.Tensor, int]] = []
        for j, stage in enumerate(self.encoder):
            conv_a, conv_b = stage[0][0], stage[1][0]
            xp = relu_pad(conv_a.forward_padded(xp), conv_b.pad)
            next_pad = self.encoder[j + 1][0][0].pad if j + 1 < len(self.encoder) else up_pad
            xp = relu_pad(conv_b.forward_padded(xp), next_pad)
            feats.append((xp, next_pad))
        skips: list[tuple[torch.Tensor, int] | None] = [*feats[:-1][::-1], None]
        ref_sizes = [(f.shape[-2], f.shape[-1] - 2 * p) for f, p in feats[:-1][::-1]]
        ref_sizes.append((image.shape[-2], image.shape[-1]))

        disps: list[torch.Tensor] = []
        xp, pad = feats[-1]
        for i, (upconv, iconv) in enumerate(zip(self.upconvs, self.iconvs, strict=True)):
            h, w = ref_sizes[i]
            out, start = upconv[0].forward_padded(xp, pad)
            parts, starts = [relu_pad(out, 0, (h, start, w))], [0]
            skip = skips[i]
            if skip is not None:
                parts.append(skip[0])
                starts.append(skip[1])
            if disps:
                parts.append(wrap_upsample2x(disps[-1], True)[..., :h, :])
                starts.append(0)
            conv = iconv[0]
            y = conv.forward_padded(pad_cat(parts, conv.pad, w, starts, fmt))
            pad = up_pad if i + 1 < len(self.upconvs) else 0
            if i >= 3:
                pad = max(pad, self.disp_heads[i - 3].conv.pad)
            xp = relu_pad(y, pad)
            if i >= 3:
                head = self.disp_heads[i - 3]
                extra = pad - head.conv.pad
                hp = xp[..., extra : xp.shape[-1] - extra] if extra else xp
                disps.append(head.alpha * torch.sigmoid(head.conv.forward_padded(hp)) + head.beta)
        return disps[::-1]
