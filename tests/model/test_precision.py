"""Which precision the networks run in (bf16 only where it is native, switchable) and that the bf16 path
gives what fp32 gives within a stated tolerance. Where the CPU has no native bf16 the bf16 path is forced
(emulated: slow, but the same numbers), so it is tested on every machine."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import cylsfm.runtime as runtime
from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera
from cylsfm.model import Predictor, load_models
from cylsfm.runtime import autocast_dtype
from helpers import untrained_checkpoint

W, H = 128, 32


def test_bf16_only_where_native_and_only_with_amp(monkeypatch) -> None:
    cpu = torch.device("cpu")
    monkeypatch.setattr(runtime, "native_bf16", lambda: False)  # AVX2 only: bf16 would be emulated
    assert autocast_dtype(cpu, True) is None
    monkeypatch.setattr(runtime, "native_bf16", lambda: True)  # AVX-512 BF16 or AMX
    assert autocast_dtype(cpu, True) == torch.bfloat16
    assert autocast_dtype(cpu, False) is None
    assert autocast_dtype(torch.device("meta"), True) is None


def _frames() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    coarse = torch.rand(3, 3, 8, 32, generator=g)
    ride = torch.nn.functional.interpolate(coarse, size=(H, W), mode="bicubic", align_corners=False).clamp(
        0, 1
    )
    ride = torch.stack(
        [torch.roll(ride[0], 2 * i, -1) * (1 - 0.05 * i) + 0.05 * i * ride[1] for i in range(4)]
    )
    return ride[1:3], torch.stack((ride[0:2], ride[2:4]), 1)


def _fit_output_layers(models) -> None:
    """Fit the last layers of untrained networks (a few hundred cheap steps on features computed once) so
    that what they predict depends on the frames: untrained, the depth barely changes with the image and the
    pose network's rotations are ~1e-4 rad, so a broken reduced-precision path (a blanked image, a negated
    pose) would stay inside the tolerances below. Fitted, the disparity follows the frames' brightness and
    the pair network answers each test pair with a motion of a few degrees."""
    from cylsfm.nn import set_wrap

    tgt, src = _frames()
    seen = {}
    # the pose head on the encoder's features of the four test pairs, to given motions
    net = models.pose_net.net
    head = net.pair.head
    first, second = tgt[:, None].expand_as(src).flatten(0, 1), src.flatten(0, 1)
    hook = head.register_forward_pre_hook(lambda module, args: seen.__setitem__("pose", args[0].detach()))
    with torch.no_grad():
        net.pair_vectors(first, second)
    hook.remove()
    motions = torch.tensor(
        [[0.4, -0.1, 0.8, 0.05, 0.02, -0.04], [-0.3, 0.05, 0.6, -0.03, 0.06, 0.02]]
    ).repeat(2, 1)
    n = first.shape[0]
    optimiser = torch.optim.Adam(head.parameters(), 0.1)
    for _ in range(200):
        pairs = head(seen["pose"])
        loss = ((pairs[:n] - pairs[n:]).view(n, 6) - motions).abs().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    # the finest decoder level and its disparity head, to a disparity that grows with the brightness
    disp = models.disp_net
    set_wrap(disp, False)  # layer by layer, so that the hook sees the finest level's input
    iconv, dhead = disp.iconvs[-1], disp.disp_heads[-1]
    hook = iconv.register_forward_pre_hook(lambda module, args: seen.__setitem__("depth", args[0].detach()))
    with torch.no_grad():
        disp(tgt)
    hook.remove()
    wanted = 1.0 + 2.0 * tgt.mean(1, keepdim=True)
    optimiser = torch.optim.Adam([*iconv.parameters(), *dhead.parameters()], 1e-2)
    for _ in range(300):
        loss = (dhead(iconv(seen["depth"])) - wanted).abs().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    set_wrap(disp, True)
    for module in (models.disp_net, models.pose_net):
        module.requires_grad_(False)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """The default recipe's networks with their output layers fitted to the test frames (see above)."""
    models = load_models(untrained_checkpoint(tmp_path_factory.mktemp("fitted"), W, H))
    _fit_output_layers(models)
    return models


@pytest.fixture
def predictors(fitted, monkeypatch) -> tuple[Predictor, Predictor]:
    """fp32 and bf16 predictors of the fitted networks, one pass of the pose network each: the fitted head
    answers the test pairs, not the pairs of a further pass (a source warped by the first pose), where
    its answers, and so their differences in precision, are arbitrary."""
    monkeypatch.setattr(runtime, "native_bf16", lambda: True)
    return Predictor(fitted, "cpu", 0, amp=False), Predictor(fitted, "cpu", 0)


def test_bf16_networks_are_copies_and_the_outputs_fp32(predictors) -> None:
    fp32, bf16 = predictors
    assert fp32.dtype is None and bf16.dtype == torch.bfloat16
    assert next(bf16.disp_net.parameters()).dtype == torch.bfloat16
    assert next(bf16.pose_net.parameters()).dtype == torch.bfloat16
    assert next(bf16.models.disp_net.parameters()).dtype == torch.float32  # the loaded weights untouched
    tgt, src = _frames()
    cam = CylindricalCamera.full(W, H)
    assert bf16.depth(tgt, cam).dtype == torch.float32
    assert bf16.poses(tgt, src, cam).dtype == torch.float64


def test_bf16_depth_and_poses_within_tolerance_of_fp32(predictors) -> None:
    """Tolerance: depth within 4% of fp32's at every pixel (bf16 keeps 8 bits of mantissa; 0.3% typical),
    each pose's translation within 5% of the largest and its rotation within 0.05 degrees."""
    fp32, bf16 = predictors
    tgt, src = _frames()
    cam = CylindricalCamera.full(W, H)
    d32, d16 = fp32.depth(tgt, cam), bf16.depth(tgt, cam)
    assert float((d16 / d32 - 1).abs().max()) < 0.04
    p32, p16 = fp32.poses(tgt, src, cam), bf16.poses(tgt, src, cam)
    t32, t16 = p32[..., :3, 3], p16[..., :3, 3]
    assert float(t32.norm(dim=-1).max()) > 0
    assert float((t16 - t32).norm(dim=-1).max()) < 0.05 * float(t32.norm(dim=-1).max())
    rot = torch.linalg.matrix_norm(p16[..., :3, :3] - p32[..., :3, :3])  # ~ angle * sqrt(2)
    assert float(rot.max()) < torch.deg2rad(torch.tensor(0.05)) * 1.5


def test_the_tolerances_would_see_a_broken_path(fitted, predictors) -> None:
    """The fitted networks' outputs depend on what they read, by far more than the tolerances above: a
    path that read blank frames, or that turned the pose network's motion round, would fail them."""
    fp32, _ = predictors
    tgt, src = _frames()
    cam = CylindricalCamera.full(W, H)
    blank = fp32.depth(torch.zeros_like(tgt), cam)
    assert float((blank / fp32.depth(tgt, cam) - 1).abs().max()) > 5 * 0.04
    with torch.no_grad():
        vectors, _ = fitted.pose_net.net(tgt, src)  # the network's part of the pose, no compass
    # negated, each rotation would move by twice its angle: ~ 2 sqrt(2) |omega| in the norm above
    assert float(vectors[..., 3:].norm(dim=-1).min()) > 5 * float(torch.deg2rad(torch.tensor(0.05)))


def test_passes_with_the_targets_depth_given_equal_the_depth_predicted(tmp_path: Path) -> None:
    """Odometry gives the further passes the depth it predicted already: at no roll, the same poses."""
    predictor = Predictor.from_checkpoint(untrained_checkpoint(tmp_path, W, H), "cpu", amp=False)
    tgt, src = _frames()
    cam = CylindricalCamera.full(W, H)
    plain = predictor.poses(tgt, src, cam)
    given = predictor.poses(tgt, src, cam, depth=predictor.depth(tgt, cam))
    torch.testing.assert_close(given, plain, atol=1e-6, rtol=0)
    with pytest.raises(CylsfmError, match="does not fit"):
        predictor.poses(tgt, src, cam, depth=torch.ones(2, 1, H, W // 2))
