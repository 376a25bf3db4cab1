"""The slot-prior scaffold: a training aid for the pair pose network, never part of the inference model.

A pair network (:class:`~cylsfm.nn.PairPoseNet`) has no bias that could carry "the usual step" while it
learns to read the motion, so early in training the depth network would see no parallax. The scaffold is a
learned 6-vector per source slot (the motion by slot that the paper's one-pass head learns in its bias),
times a gain of 10. It carries the pose alone until ``fade_start``, is blended out linearly until
``fade_end``, and from then on the pair network alone carries the motion::

    pose = (1 - w) * pair + w * prior,      w = 1, a linear fade, 0

Meanwhile the pair network is taught the prior's translation (the direction of the motion) by an L1 term
of weight ``distill * w``; the prior's side of it is detached.
"""

from __future__ import annotations

import torch
from torch import nn

from ..errors import InputError

__all__ = ["PRIOR_GAIN", "SlotPriorScaffold"]

#: The slot prior is stored divided by this gain, so that Adam's steps (about the learning rate in the
#: parameter) move it about as fast as the paper's head finds its forward step (~0.015 in 25 steps).
PRIOR_GAIN = 10.0


class SlotPriorScaffold(nn.Module):
    """A fading per-slot motion blended into the pair network's poses during training (see the module).

    Args:
        n_sources: source slots ``S``.
        fade_start: the step at which the fade begins (weight 1 before).
        fade_end: the step from which the weight is 0 (``fade_end > 0``).
        distill: weight of the distillation term at full prior weight.

    Raises:
        InputError: ``0 <= fade_start <= fade_end`` and ``fade_end > 0`` do not hold, or ``distill < 0``.
    """

    def __init__(self, n_sources: int, fade_start: int, fade_end: int, distill: float = 1.0) -> None:
        super().__init__()
        if not (0 <= fade_start <= fade_end and fade_end > 0) or distill < 0:
            raise InputError(
                f"scaffold: need 0 <= fade_start <= fade_end, fade_end > 0 and distill >= 0, got {fade_start}, "
                f"{fade_end} and {distill}"
            )
        self.fade_start, self.fade_end, self.distill = fade_start, fade_end, distill
        self.slot_prior = nn.Parameter(torch.zeros(n_sources, 6))

    def extra_repr(self) -> str:
        return f"n_sources={self.slot_prior.shape[0]}, fade={self.fade_start}..{self.fade_end}"

    def weight_at(self, step: int) -> float:
        """The prior's weight at training step ``step`` (0-based): 1, a linear fade, 0.

        Example:
            >>> s = SlotPriorScaffold(2, 300, 800)
            >>> [s.weight_at(k) for k in (0, 299, 300, 550, 800)]
            [1.0, 1.0, 1.0, 0.5, 0.0]
        """
        if step >= self.fade_end:
            return 0.0
        if step < self.fade_start:
            return 1.0
        return (self.fade_end - step) / (self.fade_end - self.fade_start)

    def forward(self, pose: torch.Tensor, step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Blend the prior into the pair network's ``pose [B,S,6]`` at ``step``.

        Returns:
            ``(pose [B,S,6], {"scaffold": the distillation term})``. The prior is in the graph even at
            weight 0, so that data-parallel training sees one set of parameters at every step.
        """
        w = self.weight_at(step)
        prior = PRIOR_GAIN * self.slot_prior.to(pose.dtype)[None].expand_as(pose)
        gap = pose[..., :3] - prior[..., :3].detach()  # the pair network learns the prior's translation
        blended = (1.0 - w) * pose + w * prior
        return blended, {"scaffold": self.distill * w * gap.float().abs().mean()}

    def unfinished(self, step: int) -> str | None:
        """A warning for a run that stops at ``step`` before the prior is faded out, else ``None``."""
        if self.weight_at(step) == 0:
            return None
        return (
            f"training stopped at step {step}, before the slot-prior scaffold was faded out (step "
            f"{self.fade_end}): the saved pose network, used without the prior, never carried the motion "
            "alone in training; train longer (or lower model.prior_fade_start/end)"
        )
