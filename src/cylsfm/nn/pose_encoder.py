"""The pose network's encoder (SfMLearner): seven stride-2 convolutions over frames stacked along channels."""

from __future__ import annotations

import torch
from torch import nn

from ..errors import InputError
from ..geometry.seam import memory_format_of
from .layers import WrapConv2d
from .padding import pad_cat, relu_pad
from .small_maps import conv2d_rows_padded

__all__ = ["Padded", "PoseEncoder", "narrow"]

#: A feature map kept padded by ``pad`` columns on each side for the convolution that reads it:
#: ``(tensor [B,C,H,W + 2 pad], pad)``.
Padded = tuple[torch.Tensor, int]


def narrow(xp: torch.Tensor, extra: int) -> torch.Tensor:
    """Drop ``extra`` columns on each side of ``xp`` ``[..., W]`` (a view)."""
    return xp[..., extra : xp.shape[-1] - extra] if extra else xp


class PoseEncoder(nn.Module):
    """Seven stride-2 convolutions + ReLU (16, 32, 64, 128, 256, 256, 256 channels; kernels 7, 5, 3, 3, 3,
    3, 3) over ``frames`` images stacked along channels, normalised as ``(x - 0.5) / 0.5``.

    Every feature map is kept padded for the convolution that reads it (circularly with ``wrap``, with
    zeros without), so that the padding costs no pass over memory beyond the ReLU's own.

    Args:
        frames: images per input (``1 + S`` for the paper's network, 2 for a pair).
        wrap: horizontal wrap-around (full 360-degree panoramas).

    Raises:
        InputError: ``frames < 2``.

    Example:
        >>> enc = PoseEncoder(frames=2)
        >>> feats = enc([torch.rand(1, 3, 32, 128), torch.rand(1, 3, 32, 128)], {})
        >>> [tuple(narrow(f, p).shape) for f, p in feats][-1]
        (1, 256, 1, 1)
    """

    channels = (16, 32, 64, 128, 256, 256, 256)
    kernels = (7, 5, 3, 3, 3, 3, 3)

    def __init__(self, frames: int, wrap: bool = True) -> None:
        super().__init__()
        if frames < 2:
            raise InputError(f"PoseEncoder: frames must be >= 2 (a target and a source), got {frames}")
        self.frames = frames
        self.wrap = wrap
        cin = (3 * frames, *self.channels[:-1])
        self.convs = nn.ModuleList(
            WrapConv2d(i, o, k, stride=2, wrap=wrap)
            for i, o, k in zip(cin, self.channels, self.kernels, strict=True)
        )

    def extra_repr(self) -> str:
        return f"frames={self.frames}, wrap={self.wrap}"

    def forward(self, frames: list[torch.Tensor], pads: dict[int, int]) -> list[Padded]:
        """The seven feature maps of ``frames`` (``[B,3,H,W]`` each, values in ``[0, 1]``).

        Args:
            frames: the input images, concatenated along channels in this order.
            pads: columns of padding wanted on each side of level ``l`` (0-based) by readers outside the
                encoder (the pose head, a decoder); at least what the next convolution needs is kept.

        Returns:
            Per level, ``(feature [B,C_l,H_l,W_l + 2 p_l], p_l)`` with ``H_l = ceil(H / 2^(l+1))``.
        """
        return self._layers(self._input(frames), pads)

    def forward_pairs(self, first: torch.Tensor, second: torch.Tensor, pads: dict[int, int]) -> list[Padded]:
        """The feature maps of the pairs ``(first, second)`` and of the swapped pairs ``(second, first)``,
        stacked along the batch: ``forward([cat(first, second), cat(second, first)], pads)`` (two frames),
        from one copy of the input.

        The first convolution is linear in its two frames, so the swapped pairs' first layer is the same
        input read by the weights with their two frames' channels swapped: one convolution with both
        weight sets (twice the output channels) on the pairs as given; its two halves of channels are then
        stacked along the batch. Equal to :meth:`forward` up to float rounding (tested); about half the
        memory traffic of building the swapped input.

        Args:
            first, second: ``[N,3,H,W]`` each (views such as an expanded target are fine).
            pads: as for :meth:`forward`.

        Returns:
            As :meth:`forward`, with batch ``2N``: the pairs first, then the swapped ones.

        Raises:
            InputError: an encoder of more than two frames.
        """
        if self.frames != 2:
            raise InputError(f"PoseEncoder.forward_pairs needs an encoder of 2 frames, not {self.frames}")
        conv = self.convs[0]
        c_in = conv.weight.shape[1] // 2
        w = conv.weight
        weight = torch.cat((w, torch.cat((w[:, c_in:], w[:, :c_in]), 1)), 0)
        bias = torch.cat((conv.bias, conv.bias)) if conv.bias is not None else None
        y = conv2d_rows_padded(self._input([first, second]), weight, bias, conv.stride, conv.pad)
        c = w.shape[0]
        y = torch.cat((y[:, :c], y[:, c:]), 0)  # [2N, C, h, w]: the pairs, then the swapped pairs
        return self._layers(y, pads, first_done=True)

    def _input(self, frames: list[torch.Tensor]) -> torch.Tensor:
        """``frames`` stacked along channels, normalised, padded for the first convolution, in the
        first convolution's dtype (a bf16 network reads fp32 images)."""
        convs = self.convs
        fmt = memory_format_of(convs[0].weight)
        dtype = convs[0].weight.dtype
        frames = [f.to(dtype) for f in frames]
        if self.wrap:
            return pad_cat(frames, convs[0].pad, memory_format=fmt).sub_(0.5).mul_(2.0)
        # zeros pad the normalised image, as a convolution's own padding would
        x = torch.cat(frames, 1).sub(0.5).mul(2.0)
        return pad_cat([x], convs[0].pad, memory_format=fmt, circular=False)

    def _layers(self, xp: torch.Tensor, pads: dict[int, int], first_done: bool = False) -> list[Padded]:
        """The convolutions from the padded input ``xp`` (or, ``first_done``, from the first
        convolution's output before its ReLU)."""
        convs = self.convs
        fmt = memory_format_of(convs[0].weight)
        padded: list[Padded] = []
        for j, conv in enumerate(convs):
            pad = max(convs[j + 1].pad if j + 1 < len(convs) else 0, pads.get(j, 0))
            if j == 0 and first_done:
                y = xp.contiguous(memory_format=fmt)
            else:
                y = conv.forward_padded(narrow(xp, padded[-1][1] - conv.pad) if padded else xp)
            xp = relu_pad(y, pad, circular=self.wrap)
            padded.append((xp, pad))
        return padded
