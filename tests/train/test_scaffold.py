"""The slot-prior scaffold (cylsfm.train.scaffold): its schedule, its blend and its distillation term."""

from __future__ import annotations

import pytest
import torch

from cylsfm.errors import InputError
from cylsfm.train.scaffold import PRIOR_GAIN, SlotPriorScaffold


def _scaffold() -> SlotPriorScaffold:
    s = SlotPriorScaffold(2, fade_start=10, fade_end=30, distill=2.0)
    with torch.no_grad():
        s.slot_prior.copy_(torch.tensor([[0, 0, -1.0, 0, 0.1, 0], [0, 0, 1.0, 0, -0.1, 0]]) * 1e-3)
    return s


def test_the_weight_fades_linearly_between_start_and_end():
    s = _scaffold()
    assert [s.weight_at(k) for k in (0, 9, 10, 20, 29, 30, 1000)] == [1.0, 1.0, 1.0, 0.5, 0.05, 0.0, 0.0]
    assert s.unfinished(30) is None and "faded out (step 30)" in s.unfinished(29)
    for bad in ((10, 5, 1.0), (0, 0, 1.0), (-1, 5, 1.0), (0, 5, -1.0)):
        with pytest.raises(InputError, match="scaffold"):
            SlotPriorScaffold(2, *bad)


def test_the_blend_and_the_distillation_term_with_their_gradients():
    """Mid-fade (weight 0.5): the pose is the blend; the term is ``distill * w * mean |t - t_prior|``; its
    gradient reaches the pair network's translation (``distill * w * sign / n``) and never the prior (the
    prior's side is detached), while the blend's gradient reaches both."""
    s = _scaffold()
    pose = (0.01 * torch.arange(12.0).view(1, 2, 6)).requires_grad_(True)
    blended, terms = s(pose, step=20)
    prior = PRIOR_GAIN * s.slot_prior[None]
    torch.testing.assert_close(blended, 0.5 * pose + 0.5 * prior)
    gap = pose[..., :3] - prior[..., :3]
    torch.testing.assert_close(terms["scaffold"], 2.0 * 0.5 * gap.abs().mean())
    g_pose, g_prior = torch.autograd.grad(terms["scaffold"], (pose, s.slot_prior), allow_unused=True)
    assert g_prior is None  # the prior is not pulled towards the pair network
    expected = torch.zeros(1, 2, 6)
    expected[..., :3] = 2.0 * 0.5 * gap.detach().sign() / gap.numel()
    torch.testing.assert_close(g_pose, expected)
    g_pose, g_prior = torch.autograd.grad(blended.sum(), (pose, s.slot_prior))
    torch.testing.assert_close(g_pose, torch.full_like(pose, 0.5))
    torch.testing.assert_close(g_prior, torch.full_like(g_prior, 0.5 * PRIOR_GAIN))


def test_after_the_fade_the_pair_network_alone_carries_the_pose():
    s = _scaffold()
    pose = torch.rand(3, 2, 6, requires_grad=True)
    blended, terms = s(pose, step=30)
    torch.testing.assert_close(blended, pose)
    assert float(terms["scaffold"].detach()) == 0
    (g,) = torch.autograd.grad(blended.sum() + terms["scaffold"], s.slot_prior)
    assert g.abs().max() == 0  # in the graph (one set of parameters for data-parallel training), at weight 0
