"""The pose networks, composed of parts: the encoder, a head, the explainability decoder, the pair network
and the visual compass.

* :class:`PoseExpNet` — SfMLearner's one-pass network: the target and its ``S`` sources in one encoder,
  a head (:mod:`~cylsfm.nn.pose_heads`), optionally the explainability masks.
* :class:`PairPoseNet` — the antisymmetric pair network ``g(t, s) - g(s, t)`` around a one-pass network
  of one source: a constant cancels, identical frames give exactly zero motion, the pose from b to a is
  the negated 6-vector of the pose from a to b, and a source's prediction does not depend on its slot.
* :class:`PoseModel` — one of them, plus the visual compass's yaw (:func:`~cylsfm.geometry.compass_yaw`)
  when asked: the network then predicts the translation and what the compass leaves of the rotation.

Every pose is ``[B,S,6]`` = ``(tx, ty, tz, rx, ry, rz)`` of ``T_tgt_to_src`` per source (translation in
depth units, axis-angle in radians). :func:`cylsfm.model.build_models` composes them from a configuration.
"""

from __future__ import annotations

import torch
from torch import nn

from ..errors import InputError, check_shape
from ..geometry.compass import compass_yaws
from .explainability import ExplainabilityDecoder
from .layers import check_input_size, init_weights
from .pose_encoder import PoseEncoder, narrow
from .pose_heads import POSE_HEADS

__all__ = ["PairPoseNet", "PoseExpNet", "PoseModel", "VisualCompass"]

Poses = tuple[torch.Tensor, list[torch.Tensor] | None]


def _check_inputs(target: torch.Tensor, sources: torch.Tensor, n_sources: int, wrap: bool) -> None:
    check_shape(target, "B,3,H,W", "target")
    check_input_size(target.shape[-1], target.shape[-2], wrap)
    dims = (target.shape[0], n_sources, 3, *target.shape[-2:])
    check_shape(sources, ",".join(str(n) for n in dims), "sources")


class PoseExpNet(nn.Module):
    """SfMLearner's pose / explainability network, wrap-around aware (one pass over all frames).

    Args:
        n_sources: ``S``.
        explainability: build and run the explainability decoder.
        wrap: horizontal wrap-around (widths multiples of 128).
        pose_head: ``"mean"`` (the paper's) or ``"equivariant"`` (full panoramas).

    Raises:
        InputError: ``n_sources < 1`` or an unknown head.
    """

    def __init__(
        self, n_sources: int = 2, explainability: bool = True, wrap: bool = True, pose_head: str = "mean"
    ) -> None:
        super().__init__()
        if n_sources < 1:
            raise InputError(f"PoseExpNet: n_sources must be >= 1, got {n_sources}")
        if pose_head not in POSE_HEADS:
            raise InputError(
                f"PoseExpNet: pose_head must be one of {', '.join(POSE_HEADS)}, got {pose_head!r}"
            )
        self.n_sources = n_sources
        self.wrap = wrap
        self.encoder = PoseEncoder(1 + n_sources, wrap)
        self.head = POSE_HEADS[pose_head](PoseEncoder.channels[-1], n_sources, wrap)
        self.explain = ExplainabilityDecoder(n_sources, wrap) if explainability else None
        init_weights(self)

    check_input_size = staticmethod(check_input_size)

    def forward(self, target: torch.Tensor, sources: torch.Tensor) -> Poses:
        """``target [B,3,H,W]``, ``sources [B,S,3,H,W]`` in ``[0, 1]`` (``H >= 32``; with wrap ``W`` a
        multiple of 128) -> ``(pose [B,S,6], masks)``: four masks ``[B,S,H_s,W_s]``, finest first, or
        ``None`` without explainability. Raises ``InputError`` for wrong shapes or sizes."""
        _check_inputs(target, sources, self.n_sources, self.wrap)
        pads = {len(PoseEncoder.channels) - 1: self.head.conv.pad}
        if self.explain is not None:
            pads[ExplainabilityDecoder.level] = self.explain.in_pad
        features = self.encoder([target, *sources.unbind(1)], pads)
        pose = self.head(narrow(*features[-1]))
        masks = self.explain(features, target) if self.explain is not None else None
        return pose, masks

    def pair_poses(self, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        """The poses of a one-source network without explainability read on the pairs ``(first,
        second)`` and on the swapped pairs ``(second, first)``: ``[2N,1,6]`` (the pairs, then the swapped),
        as ``forward`` of ``cat(first, second)`` with sources ``cat(second, first)`` would give (up to
        float rounding), from one copy of the input (:meth:`PoseEncoder.forward_pairs`).

        Raises:
            InputError: a network of more than one source or with explainability.
        """
        if self.n_sources != 1 or self.explain is not None:
            raise InputError("PoseExpNet.pair_poses needs a one-source network without explainability")
        _check_inputs(first, second[:, None], 1, self.wrap)
        pads = {len(PoseEncoder.channels) - 1: self.head.conv.pad}
        features = self.encoder.forward_pairs(first, second, pads)
        return self.head(narrow(*features[-1]))


class PairPoseNet(nn.Module):
    """The antisymmetric pair network: each (target, source) pair and its swap through one
    :class:`PoseExpNet` of one source, ``pose = g(t, s) - g(s, t)``. No explainability masks.

    Args:
        n_sources: ``S``.
        wrap: horizontal wrap-around.
        pose_head: ``"mean"`` or ``"equivariant"``.

    Example:
        >>> net = PairPoseNet(2).eval()
        >>> t, s = torch.rand(1, 3, 32, 128), torch.rand(1, 2, 3, 32, 128)
        >>> a = net(t, s)[0][0, 0]
        >>> b = net(s[:, 0], t[:, None].expand(1, 2, 3, 32, 128))[0][0, 0]
        >>> bool(torch.allclose(a, -b, atol=1e-6))
        True
    """

    def __init__(self, n_sources: int = 2, wrap: bool = True, pose_head: str = "mean") -> None:
        super().__init__()
        if n_sources < 1:
            raise InputError(f"PairPoseNet: n_sources must be >= 1, got {n_sources}")
        self.n_sources = n_sources
        self.wrap = wrap
        self.pair = PoseExpNet(1, explainability=False, wrap=wrap, pose_head=pose_head)

    def extra_repr(self) -> str:
        return f"n_sources={self.n_sources}"

    def forward(self, target: torch.Tensor, sources: torch.Tensor) -> Poses:
        """As :meth:`PoseExpNet.forward`; the masks are always ``None``."""
        _check_inputs(target, sources, self.n_sources, self.wrap)
        b, s = sources.shape[:2]
        first = target[:, None].expand_as(sources).flatten(0, 1)  # [B*S,3,H,W]
        return self.pair_vectors(first, sources.flatten(0, 1)).view(b, s, 6), None

    def pair_vectors(self, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        """The pose 6-vectors from ``first [N,3,H,W]`` to ``second [N,3,H,W]``, pair by pair: ``[N,6]``
        (the pose from ``second`` to ``first`` is exactly its negative)."""
        n = first.shape[0]
        pairs = self.pair.pair_poses(first, second)
        return (pairs[:n] - pairs[n:]).view(n, 6)


class VisualCompass(nn.Module):
    """The yaw from a target to each source, read in closed form by the visual compass (the circular
    column shift that aligns two full panoramas; no weights, no gradient), as pose 6-vectors ``[B,S,6]``
    that are zero but for ``ry``."""

    def forward(self, target: torch.Tensor, sources: torch.Tensor) -> torch.Tensor:
        """``target [B,3,H,W]``, ``sources [B,S,3,H,W]`` (full panoramas) -> ``[B,S,6]``."""
        with torch.no_grad():
            return self.vectors(compass_yaws(target.float(), sources.float()))

    @staticmethod
    def vectors(yaws: torch.Tensor) -> torch.Tensor:
        """Yaws ``[B,S]`` (radians) -> pose 6-vectors ``[B,S,6]``, zero but for ``ry``."""
        yaw = yaws[..., None]
        zeros = torch.zeros_like(yaw)
        return torch.cat((zeros, zeros, zeros, zeros, yaw, zeros), -1)


class PoseModel(nn.Module):
    """A pose network and, optionally, the visual compass's yaw added to its rotation.

    Args:
        net: a :class:`PoseExpNet` or :class:`PairPoseNet`.
        compass: add :class:`VisualCompass`'s yaw (full panoramas: ``net.wrap``).

    Raises:
        InputError: the compass without wrap-around.
    """

    def __init__(self, net: PoseExpNet | PairPoseNet, compass: bool = False) -> None:
        super().__init__()
        if compass and not net.wrap:
            raise InputError("the visual compass needs full 360-degree panoramas (wrap=True)")
        self.net = net
        self.compass = VisualCompass() if compass else None

    @property
    def n_sources(self) -> int:
        return self.net.n_sources

    @property
    def pairs(self) -> bool:
        """Whether the network reads frame pairs (:class:`PairPoseNet`)."""
        return isinstance(self.net, PairPoseNet)

    def forward(self, target: torch.Tensor, sources: torch.Tensor) -> Poses:
        """As :meth:`PoseExpNet.forward`, with the compass's yaw added."""
        pose, masks = self.net(target, sources)
        return self.with_compass(pose, target, sources), masks

    def with_compass(
        self,
        pose: torch.Tensor,
        target: torch.Tensor,
        sources: torch.Tensor,
        yaws: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``pose [B,S,6]`` plus the compass's yaw from ``target`` to ``sources`` (unchanged without it);
        in fp32 when ``pose`` is bf16 or fp16 (a network under autocast), so that the yaw is not rounded.
        ``yaws`` ``[B,S]``: those yaws computed already (:func:`~cylsfm.geometry.window_yaws`)."""
        if self.compass is None:
            return pose
        if pose.dtype in (torch.bfloat16, torch.float16):
            pose = pose.float()
        added = self.compass(target, sources) if yaws is None else self.compass.vectors(yaws)
        return pose + added.to(pose.dtype)
