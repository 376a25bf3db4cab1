"""The pose heads: from the pose encoder's deepest features to one 6-vector per source.

Each 6-vector is ``(tx, ty, tz, rx, ry, rz)``: the translation (in the scale of the predicted depth) and
the axis-angle rotation (radians) of ``T_tgt_to_src``, which maps points of the target camera frame into
the source camera (axes x right, y down, z forward).
"""

from __future__ import annotations

import torch
from torch import nn

from ..errors import InputError, check_shape
from .layers import WrapConv2d

__all__ = ["POSE_HEADS", "EquivariantPoseHead", "MeanPoseHead"]


class MeanPoseHead(nn.Module):
    """The paper's head: a 1x1 convolution to ``6 S`` channels, averaged over all positions, times 0.01.

    With wrap-around the pose is exactly invariant to a common horizontal roll of all frames by a multiple
    of the encoder's stride (128 px), although such a roll is a yaw of the camera.

    Args:
        in_channels: channels of the features read.
        n_sources: ``S``.
        wrap: horizontal wrap-around.
    """

    def __init__(self, in_channels: int, n_sources: int, wrap: bool = True) -> None:
        super().__init__()
        if n_sources < 1:
            raise InputError(f"{type(self).__name__}: n_sources must be >= 1, got {n_sources}")
        self.n_sources = n_sources
        self.conv = WrapConv2d(in_channels, 6 * n_sources, 1, wrap=wrap)

    def extra_repr(self) -> str:
        return f"n_sources={self.n_sources}"

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """``features [B,C,H_f,W_f]`` -> poses ``[B,S,6]``."""
        check_shape(features, f"B,{self.conv.in_channels},H,W", "features")
        raw = self.conv(features)
        return 0.01 * raw.mean(dim=(2, 3)).view(features.shape[0], self.n_sources, 6)


class EquivariantPoseHead(MeanPoseHead):
    """A yaw-equivariant head for full panoramas: every column ``j`` of the features (azimuth
    ``theta_j = 2 pi j / W_f - pi``, the azimuth of input column ``128 j`` when ``cx = W / 2``) predicts the
    translation and rotation in its own azimuthal frame; each is turned by ``theta_j`` about the vertical
    axis before the average. Rolling all frames by ``128 m`` pixels (a yaw ``Delta = 2 pi 128 m / W``) then
    turns the output exactly: ``t -> Q t``, ``omega -> Q omega`` with ``Q = yaw_matrix(Delta)``. At 256 px
    wide that is half turns only (2 columns).

    Example:
        >>> head = EquivariantPoseHead(4, 1)
        >>> f = torch.rand(1, 4, 1, 2)
        >>> a, b = head(f), head(f.roll(1, -1))  # a half turn: x and z change sign
        >>> torch.allclose(b[0, 0, [0, 2, 3, 5]], -a[0, 0, [0, 2, 3, 5]], atol=1e-7)
        True
    """

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """``features [B,C,H_f,W_f]`` -> poses ``[B,S,6]``."""
        check_shape(features, f"B,{self.conv.in_channels},H,W", "features")
        raw = self.conv(features)
        cols = raw.mean(dim=2).view(features.shape[0], self.n_sources, 2, 3, raw.shape[-1])
        return 0.01 * _rotate_columns_and_average(cols)


def _rotate_columns_and_average(cols: torch.Tensor) -> torch.Tensor:
    """``[B,S,2,3,W_f]`` per-column (t, omega) in the columns' own azimuthal frames -> ``[B,S,6]``.

    Column ``j`` sits at azimuth ``theta_j = 2 pi j / W_f - pi``; its vectors are rotated by
    ``yaw_matrix(theta_j)`` (``x' = cos x + sin z``, ``z' = -sin x + cos z``) and averaged over columns.
    """
    w = cols.shape[-1]
    theta = torch.arange(w, device=cols.device, dtype=torch.float32) * (2 * torch.pi / w) - torch.pi
    c, s_ = torch.cos(theta).to(cols.dtype), torch.sin(theta).to(cols.dtype)
    x, y, z = cols[..., 0, :], cols[..., 1, :], cols[..., 2, :]
    rotated = torch.stack((c * x + s_ * z, y, -s_ * x + c * z), -2)  # [B,S,2,3,W_f]
    return rotated.mean(-1).flatten(2)


#: The heads by the name a configuration gives them (``model.pose_head``).
POSE_HEADS: dict[str, type[MeanPoseHead]] = {"mean": MeanPoseHead, "equivariant": EquivariantPoseHead}
