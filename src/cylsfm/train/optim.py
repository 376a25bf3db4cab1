"""Adam for networks kept in channels-last memory.

PyTorch's fused Adam updates dense tensors in their default (contiguous) order: each parameter that is
not contiguous (a 4-D convolution weight kept channels-last, as the trainer keeps the networks on
CPUs where channels-last convolutions are faster) is copied out with its gradient and both moments and
copied back, every step; on the default networks that copying is a sizeable part of the update
(BENCHMARKS.md links the measurements). :class:`Adam` hands the fused update such tensors through the
permutation that makes them contiguous (``[O, I, kh, kw]`` stored channels-last is a contiguous
``[O, kh, kw, I]``): the same memory, the same element-wise update, nothing copied.
"""

from __future__ import annotations

import torch

__all__ = ["Adam"]

_TO_MEMORY_ORDER = (0, 2, 3, 1)  # [O, I, kh, kw] channels-last -> contiguous [O, kh, kw, I]
_MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")


def _channels_last_only(t: torch.Tensor) -> bool:
    return t.dim() == 4 and not t.is_contiguous() and t.is_contiguous(memory_format=torch.channels_last)


class Adam(torch.optim.Adam):
    """``torch.optim.Adam`` (same arguments, same results, same ``state_dict``) whose fused update does not
    copy channels-last parameters.

    With ``fused=True`` the fused update of each channels-last 4-D parameter reads the parameter, its
    gradient and its moments through views in their memory order (contiguous). The parameters and their
    gradients are never reshaped or replaced; the moments are kept in the optimiser's state in their
    parameter's shape and memory format (moments loaded contiguous, as a checkpoint may hold them, are
    laid out channels-last there once). Otherwise this is ``torch.optim.Adam``.
    """

    def _init_group(  # type: ignore[override]
        self,
        group: dict,
        params: list[torch.Tensor],
        grads: list[torch.Tensor],
        exp_avgs: list[torch.Tensor],
        exp_avg_sqs: list[torch.Tensor],
        max_exp_avg_sqs: list[torch.Tensor],
        state_steps: list[torch.Tensor],
    ) -> bool:
        """torch's lists of the tensors that the update of ``group`` reads, with every channels-last
        parameter's tensors replaced by their views in memory order (fused updates only)."""
        has_complex = super()._init_group(
            group, params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, state_steps
        )
        if not group["fused"]:
            return has_complex
        moments = (exp_avgs, exp_avg_sqs, max_exp_avg_sqs if group["amsgrad"] else None)
        for i, p in enumerate(params):
            if not (_channels_last_only(p) and _channels_last_only(grads[i])):
                continue
            state = self.state[p]
            for name, listed in zip(_MOMENTS, moments, strict=True):
                if listed is not None:
                    listed[i] = self._channels_last_moment(state, name).permute(_TO_MEMORY_ORDER)
            params[i] = p.permute(_TO_MEMORY_ORDER)
            grads[i] = grads[i].permute(_TO_MEMORY_ORDER)
        return has_complex

    @staticmethod
    def _channels_last_moment(state: dict, name: str) -> torch.Tensor:
        """The moment ``name`` of a channels-last parameter, laid out channels-last in ``state``."""
        moment = state[name]
        if not moment.is_contiguous(memory_format=torch.channels_last):
            moment = state[name] = moment.contiguous(memory_format=torch.channels_last)
        return moment
