"""SfMLearner's explainability decoder: per-source masks of the pixels that view synthesis can explain."""

from __future__ import annotations

import torch
from torch import nn

from ..errors import InputError
from .layers import WrapConv2d, WrapConvTranspose2d
from .padding import relu_pad
from .pose_encoder import Padded, narrow

__all__ = ["ExplainabilityDecoder"]


class ExplainabilityDecoder(nn.Module):
    """From the pose encoder's level 5 (0-based 4): five up-convolutions + ReLU (256, 128, 64, 32, 16
    channels), each cropped to the size of the matching encoder feature (levels 4, 3, 2, 1, the input),
    with sigmoid masks (3x3 convolutions to ``S`` channels) at the last four.

    Args:
        n_sources: ``S``, one mask per source.
        wrap: horizontal wrap-around.
        in_channels: channels of the encoder's level 5.
    """

    channels = (256, 128, 64, 32, 16)
    #: The encoder level (0-based) the decoder starts from.
    level = 4

    def __init__(self, n_sources: int, wrap: bool = True, in_channels: int = 256) -> None:
        super().__init__()
        if n_sources < 1:
            raise InputError(f"ExplainabilityDecoder: n_sources must be >= 1, got {n_sources}")
        self.n_sources = n_sources
        self.wrap = wrap
        cin = (in_channels, *self.channels[:-1])
        self.upconvs = nn.ModuleList(
            WrapConvTranspose2d(i, o, 3, stride=2, wrap=wrap) for i, o in zip(cin, self.channels, strict=True)
        )
        self.mask_heads = nn.ModuleList(WrapConv2d(c, n_sources, 3, wrap=wrap) for c in self.channels[1:])

    def extra_repr(self) -> str:
        return f"n_sources={self.n_sources}, wrap={self.wrap}"

    @property
    def in_pad(self) -> int:
        """Columns of padding the decoder needs on each side of its input (see :class:`PoseEncoder`)."""
        return max(max(u.wrap_left, u.wrap_right) for u in self.upconvs)

    def forward(self, features: list[Padded], image: torch.Tensor) -> list[torch.Tensor]:
        """Masks from the encoder's padded ``features`` (its level 5 padded by at least :attr:`in_pad`).

        Args:
            features: :class:`~cylsfm.nn.pose_encoder.PoseEncoder`'s output.
            image: the target ``[B,3,H,W]`` (its size is the finest mask's).

        Returns:
            Four masks ``[B,S,H_s,W_s]`` in ``(0, 1)``, finest first (``H_0 = H``, ``H_s = ceil(H_{s-1}/2)``).
        """
        refs = [*(narrow(f, p) for f, p in features[3::-1]), image]  # levels 4, 3, 2, 1 (1-based), input
        masks: list[torch.Tensor] = []
        xp, pad = features[self.level]
        for i, upconv in enumerate(self.upconvs):
            h, w = refs[i].shape[-2:]
            out, start = upconv.forward_padded(xp, pad)
            pad = self.in_pad if i + 1 < len(self.upconvs) else 0
            if i >= 1:
                pad = max(pad, self.mask_heads[i - 1].pad)
            xp = relu_pad(out, pad, (h, start, w), circular=self.wrap)
            if i >= 1:
                head = self.mask_heads[i - 1]
                masks.append(torch.sigmoid(head.forward_padded(narrow(xp, pad - head.pad))))
        return masks[::-1]
