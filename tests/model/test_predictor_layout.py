"""The Predictor's networks in channels-last memory where convolutions prefer it, the caller's untouched."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cylsfm.geometry import CylindricalCamera
from cylsfm.model import Predictor, build_models, preset
from cylsfm.model import predictor as predictor_module
from cylsfm.model.build import LoadedModels

W, H = 128, 32


def _models() -> LoadedModels:
    cfg = preset("default")
    cfg.data.width, cfg.data.height = W, H
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    return LoadedModels(disp.eval(), pose.eval(), cfg, 0, Path("untrained"))


def _channels_last(net: torch.nn.Module) -> bool:
    weights = [p for p in net.parameters() if p.dim() == 4]
    return all(w.is_contiguous(memory_format=torch.channels_last) for w in weights)


@pytest.mark.parametrize("prefers", [True, False])
def test_layout_follows_the_device_and_outputs_do_not(monkeypatch, prefers):
    monkeypatch.setattr(predictor_module, "prefers_channels_last", lambda device: prefers)
    models = _models()
    pred = Predictor(models, amp=False)
    assert _channels_last(pred.disp_net) == prefers and _channels_last(pred.pose_net.net) == prefers
    assert (pred.disp_net is models.disp_net) == (not prefers)
    assert not _channels_last(models.disp_net)  # the caller's networks are left as they were
    images = torch.rand(2, 3, H, W)
    cam = CylindricalCamera.full(W, H)
    with torch.no_grad():
        expected = 1.0 / models.disp_net(images)[0]
    torch.testing.assert_close(pred.depth(images, cam), expected, rtol=1e-4, atol=1e-4)
    sources = torch.rand(2, 2, 3, H, W)
    monkeypatch.setattr(predictor_module, "prefers_channels_last", lambda device: not prefers)
    other = Predictor(models, amp=False)
    mine, theirs = pred.poses(images, sources, cam), other.poses(images, sources, cam)
    # untrained, the translations are ~1e-5 long: compared to their own length, not to a fixed tolerance
    t_mine, t_theirs = mine[..., :3, 3], theirs[..., :3, 3]
    length = float(t_theirs.norm(dim=-1).min())
    assert length > 0
    gap = float((t_mine - t_theirs).norm(dim=-1).max())
    assert gap < 1e-3 * length, f"translations differ by {gap:.3g}, {gap / length:.1%} of their length"
    torch.testing.assert_close(mine[..., :3, :3], theirs[..., :3, :3], rtol=0, atol=1e-6)
    rotation = float((theirs[..., :3, :3] - torch.eye(3, dtype=theirs.dtype)).abs().max())
    turned = float((mine[..., :3, :3] - theirs[..., :3, :3]).abs().max())
    assert turned < 1e-3 * rotation, f"rotations differ by {turned:.3g} of {rotation:.3g}"
