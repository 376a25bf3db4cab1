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
    """The project's fused Adam against torch's: its fused Adam (which copies channels-last tensors: the
    same arithmetic, the same results) and, ``fused=False``, its reference for-loop implementation (the
    same update to rounding)."""
    ours, theirs = _net(), _net()
    assert any(p.dim() == 4 and not p.is_contiguous() for p in ours.parameters())
    opt = Adam(ours.parameters(), lr=1e-2, weight_decay=1e-4, fused=True)
    ref = torch.optim.Adam(theirs.parameters(), lr=1e-2, weight_decay=1e-4, fused=fused, foreach=False)
    _train(ours, opt, 4)
    _train(theirs, ref, 4)
    tolerance = {"rtol": 0, "atol": 1e-7} if fused else {"rtol": 1e-6, "atol": 1e-7}
    for a, b in zip(ours.parameters(), theirs.parameters(), strict=True):
        torch.testing.assert_close(a, b, **tolerance)
        assert a.stride() == b.stride()  # the parameters keep their shape and memory format
        state = opt.state[a]
        assert state["exp_avg"].shape == a.shape and state["exp_avg"].stride() == a.stride()
        torch.testing.assert_close(state["exp_avg_sq"], ref.state[b]["exp_avg_sq"], **tolerance)
        assert a.grad.shape == a.shape


def test_the_fused_update_reads_parameters_in_place(monkeypatch):
    """The fused kernel gets every tensor contiguous (nothing for it to copy) while the parameters keep
    their own shape and memory, during the step too: none is reshaped or replaced."""
    net = _net()
    params = list(net.parameters())
    layout = [(p.shape, p.stride(), p.data_ptr()) for p in params]
    opt = Adam(params, lr=1e-2, fused=True)
    seen = []
    kernel = torch._fused_adam_

    def checked(*args, **kwargs):
        assert [(p.shape, p.stride(), p.data_ptr()) for p in params] == layout
        seen.extend(t for tensors in args[:4] for t in tensors)
        return kernel(*args, **kwargs)

    monkeypatch.setattr(torch, "_fused_adam_", checked)
    _train(net, opt, 2)
    assert len(seen) == 2 * 4 * len(params) and all(t.is_contiguous() for t in seen)
    assert [(p.shape, p.stride(), p.data_ptr()) for p in params] == layout


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
