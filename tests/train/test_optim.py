"""Adam through channels-last parameters' memory order against torch's own Adam."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from cylsfm.train.optim import Adam


def _net() -> nn.Module:
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 8, 3), nn.ReLU(), nn.Conv2d(8, 4, 1), nn.Flatten(), nn.LazyLinear(2))
    net(torch.rand(1, 3, 8, 8))
    return net.to(memory_format=torch.channels_last)


def _train(net: nn.Module, opt: torch.optim.Optimizer, steps: int) -> None:
    gen = torch.Generator().manual_seed(1)
    for _ in range(steps):
        x = torch.rand(2, 3, 8, 8, generator=gen).contiguous(memory_format=torch.channels_last)
        opt.zero_grad(set_to_none=True)
        net(x).square().mean().backward()
        opt.step()


@pytest.mark.parametrize("fused", [True, False])
def test_same_updates_as_torch_adam(fused):
    ours, theirs = _net(), _net()
    assert any(p.dim() == 4 and not p.is_contiguous() for p in ours.parameters())
    opt = Adam(ours.parameters(), lr=1e-2, weight_decay=1e-4, fused=fused)
    _train(ours, opt, 4)
    _train(theirs, torch.optim.Adam(theirs.parameters(), lr=1e-2, weight_decay=1e-4, fused=fused), 4)
    for a, b in zip(ours.parameters(), theirs.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-7)
        assert a.stride() == b.stride()  # the parameters keep their shape and memory format
        state = opt.state[a]
        assert state["exp_avg"].shape == a.shape and state["exp_avg"].stride() == a.stride()
        assert a.grad.shape == a.shape


def test_state_dict_is_torch_adams_both_ways():
    ours, theirs = _net(), _net()
    opt = Adam(ours.parameters(), lr=1e-2, fused=True)
    ref = torch.optim.Adam(theirs.parameters(), lr=1e-2, fused=True)
    _train(ours, opt, 2)
    _train(theirs, ref, 2)
    # resume each from the other's saved state (moments saved contiguous, as a checkpoint may hold them)
    saved = copy.deepcopy(ref.state_dict())
    for st in saved["state"].values():
        st["exp_avg"], st["exp_avg_sq"] = st["exp_avg"].contiguous(), st["exp_avg_sq"].contiguous()
    opt2 = Adam(ours.parameters(), lr=1e-2, fused=True)
    ours.load_state_dict(theirs.state_dict())
    opt2.load_state_dict(saved)
    ref2 = torch.optim.Adam(theirs.parameters(), lr=1e-2, fused=True)
    ref2.load_state_dict(
        copy.deepcopy(opt.state_dict()) | {"state": copy.deepcopy(ref.state_dict()["state"])}
    )
    _train(ours, opt2, 2)
    _train(theirs, ref2, 2)
    for a, b in zip(ours.parameters(), theirs.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-7)
