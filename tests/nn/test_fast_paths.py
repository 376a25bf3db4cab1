"""The pose network's fast paths against the plain computations they replace: the pairs read from one
copy of the input (:meth:`PoseEncoder.forward_pairs`) and the compass's target spectrum computed once per
target (:func:`compass_yaws`) and each frame's spectrum once for the windows of a ride (:func:`window_yaws`)."""

from __future__ import annotations

import pytest
import torch

from cylsfm.errors import InputError, ShapeError
from cylsfm.geometry import compass_yaw, compass_yaws, window_yaws
from cylsfm.nn import PairPoseNet, PoseExpNet


def _plain_pairs(net: PairPoseNet, target: torch.Tensor, sources: torch.Tensor) -> torch.Tensor:
    """``g(t, s) - g(s, t)`` with both orders built as inputs and run through the one-source network."""
    b, s = sources.shape[:2]
    first = target[:, None].expand_as(sources).flatten(0, 1)
    second = sources.flatten(0, 1)
    pairs, _ = net.pair(torch.cat((first, second)), torch.cat((second, first))[:, None])
    return (pairs[: b * s] - pairs[b * s :]).view(b, s, 6)


@pytest.mark.parametrize(
    ("wrap", "channels_last", "head"),
    [(True, True, "equivariant"), (True, False, "mean"), (False, False, "mean")],
)
def test_pairs_from_one_input_equal_both_orders_built(wrap: bool, channels_last: bool, head: str) -> None:
    torch.manual_seed(0)
    net = PairPoseNet(2, wrap=wrap, pose_head=head)
    if channels_last:
        net = net.to(memory_format=torch.channels_last)
    target = torch.rand(2, 3, 64, 256, requires_grad=True)
    sources = torch.rand(2, 2, 3, 64, 256)
    fast = net(target, sources)[0]
    plain = _plain_pairs(net, target, sources)
    scale = float(plain.abs().max())
    assert scale > 0
    torch.testing.assert_close(fast, plain, atol=1e-5 * scale, rtol=0)
    # the same gradients for training: of the weights (both orders' first layer) and of the input
    weights = [net.pair.encoder.convs[0].weight, net.pair.head.conv.weight]
    g_fast = torch.autograd.grad((fast * torch.arange(12.0).view(1, 2, 6)).sum(), [*weights, target])
    g_plain = torch.autograd.grad((plain * torch.arange(12.0).view(1, 2, 6)).sum(), [*weights, target])
    for a, b in zip(g_fast, g_plain, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5 * float(b.abs().max()), rtol=0)


def test_pair_poses_needs_a_one_source_network_without_masks() -> None:
    x = torch.rand(1, 3, 32, 128)
    with pytest.raises(InputError, match="one-source"):
        PoseExpNet(2, explainability=False).pair_poses(x, x)
    with pytest.raises(InputError, match="one-source"):
        PoseExpNet(1, explainability=True).pair_poses(x, x)


@pytest.mark.parametrize("masked", [False, True])
def test_compass_of_each_source_equals_each_pair_alone(masked: bool) -> None:
    g = torch.Generator().manual_seed(1)
    target = torch.rand(3, 3, 32, 128, generator=g)
    sources = torch.stack(
        (torch.roll(target, 5, -1) + 0.1 * torch.rand(3, 3, 32, 128, generator=g), target), 1
    )
    mask = (torch.rand(1, 1, 32, 128, generator=g) > 0.2).float() if masked else None
    yaws = compass_yaws(target, sources, mask)
    each = torch.stack([compass_yaw(target, sources[:, i], mask) for i in range(2)], 1)
    torch.testing.assert_close(yaws, each, atol=1e-12, rtol=0)
    assert yaws[:, 1].abs().max() < 1e-9  # a source identical to its target
    with pytest.raises(ShapeError, match="do not fit"):
        compass_yaws(target, sources[:2])
    with pytest.raises(ShapeError, match="mask"):
        compass_yaws(target, sources, torch.ones(3, 1, 32, 128))


@pytest.mark.parametrize("k", [1, 2])
def test_window_yaws_equal_each_windows_compass_yaws(k: int) -> None:
    g = torch.Generator().manual_seed(3)
    base = torch.rand(1, 3, 16, 128, generator=g)
    frames = torch.cat(
        [torch.roll(base, 3 * i, -1) + 0.05 * torch.rand(1, 3, 16, 128, generator=g) for i in range(7)]
    )
    n = frames.shape[0]
    sources = torch.stack([frames[k + o : n - k + o] for o in range(-k, k + 1) if o], 1)
    yaws = window_yaws(frames, k)
    torch.testing.assert_close(yaws, compass_yaws(frames[k : n - k], sources), atol=1e-12, rtol=0)
    assert yaws.shape == (n - 2 * k, 2 * k) and float(yaws.abs().min()) > 0.1  # every pair turned
    with pytest.raises(ShapeError, match="no window"):
        window_yaws(frames[: 2 * k], k)
