"""Adam for networks kept in channels-last memory.

PyTorch's fused Adam updates dense tensors in their default (contiguous) order: each parameter that is
not contiguous (a 4-D convolution weight kept channels-last, as the trainer keeps the networks on
CPUs where channels-last convolutions are faster) is copied out with its gradient and both moments and
copied back, every step. For the default networks that is about 22 ms of a 0.46 s step on an Intel Xeon
with AMX (512x128, batch 4: the update of their 34 M parameters 23 ms through contiguous views against
45-53 ms), BENCHMARKS.md. :class:`Adam` lets the fused update read such tensors through the permutation
that makes them contiguous (``[O, I, kh, kw]`` stored channels-last is a contiguous ``[O, kh, kw, I]``):
the same memory, the same element-wise update, nothing copied.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["Adam"]

_TO_MEMORY_ORDER = (0, 2, 3, 1)  # [O, I, kh, kw] channels-last -> contiguous [O, kh, kw, I]
_BACK = (0, 3, 1, 2)
_MOMENTS = ("exp_avg", "exp_avg_sq")


def _channels_last_only(t: torch.Tensor) -> bool:
    return t.dim() == 4 and not t.is_contiguous() and t.is_contiguous(memory_format=torch.channels_last)


class Adam(torch.optim.Adam):
    """``torch.optim.Adam`` (same arguments, same results, same ``state_dict``) whose fused update does not
    copy channels-last parameters.

    With ``fused=True`` each channels-last 4-D parameter, its gradient and its moments are handed to the
    fused update through their contiguous permutation for the duration of :meth:`step`, and put back in
    their own shape after it (also when the step raises). Otherwise this is ``torch.optim.Adam``.
    """

    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # type: ignore[override]
        """One Adam step over every parameter with a gradient (``closure``: as ``torch.optim.Adam``)."""
        if not self.defaults.get("fused"):
            return super().step(closure)
        permuted = []
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None or not _channels_last_only(p) or not _channels_last_only(p.grad):
                    continue
                grad = p.grad
                p.data = p.data.permute(_TO_MEMORY_ORDER)
                p.grad = grad.permute(_TO_MEMORY_ORDER)
                state = self.state.get(p, {})
                for name in _MOMENTS:
                    if name in state:  # moments loaded from a checkpoint may come contiguous
                        moment = state[name].contiguous(memory_format=torch.channels_last)
                        state[name] = moment.permute(_TO_MEMORY_ORDER)
                permuted.append(p)
        try:
            return super().step(closure)
        finally:
            for p in permuted:
                p.data = p.data.permute(_BACK)
                p.grad = p.grad.permute(_BACK)
                state = self.state.get(p, {})
                for name in _MOMENTS:
                    if name in state:  # the first step created them in the permuted shape
                        state[name] = state[name].permute(_BACK)
