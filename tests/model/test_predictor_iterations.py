"""The pose network applied again to the source warped by its own pose (``Predictor.pose_iterations``)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch import nn

from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera, compass_yaw
from cylsfm.model import Predictor
from cylsfm.model.build import LoadedModels
from cylsfm.model.config import preset
from cylsfm.model.predictor import DEFAULT_POSE_ITERATIONS
from helpers import untrained_checkpoint

W, H = 128, 32


class _HalfCompassNet(nn.Module):
    """A pair pose network that reads half of the yaw between the target and each source (the visual
    compass's, no translation): a network that under-reads the motion, each pass by half."""

    antisymmetric = True

    def forward(self, target: torch.Tensor, sources: torch.Tensor):
        b, s = sources.shape[:2]
        yaw = compass_yaw(target[:, None].expand_as(sources).flatten(0, 1), sources.flatten(0, 1))
        vec = torch.zeros(b, s, 6)
        vec[..., 4] = 0.5 * yaw.view(b, s)
        return vec, None


class _FlatDisp(nn.Module):
    def forward(self, x: torch.Tensor):
        return [torch.ones(x.shape[0], 1, *x.shape[-2:])]


def _predictor(iterations: int | None) -> Predictor:
    cfg = preset("default")
    cfg.data.width, cfg.data.height = W, H
    models = LoadedModels(_FlatDisp(), _HalfCompassNet(), cfg, 0, Path("stub"))  # type: ignore[arg-type]
    return Predictor(models, pose_iterations=iterations)


def _panorama() -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    coarse = torch.rand(1, 3, 8, 16, generator=g)
    return torch.nn.functional.interpolate(coarse, size=(H, W), mode="bicubic", align_corners=False).clamp(
        0, 1
    )


@pytest.mark.parametrize(("iterations", "fraction"), [(0, 0.5), (1, 0.75), (3, 0.9375)])
def test_each_pass_reads_what_the_warp_left(iterations: int, fraction: float) -> None:
    """A camera turned by 8 columns (22.5 degrees): a network that reads half of any yaw gets
    1 - 2^-(n+1) of it after n further passes over its own warp."""
    tgt = _panorama()
    src = torch.roll(tgt, 8, -1)[:, None].repeat(1, 2, 1, 1, 1)
    pose = _predictor(iterations).poses(tgt, src, CylindricalCamera.full(W, H))
    true = float(compass_yaw(tgt, src[:, 0]))
    assert abs(true) == pytest.approx(2 * math.pi * 8 / W, rel=0.02)
    yaw = math.atan2(float(pose[0, 0, 0, 2]), float(pose[0, 0, 0, 0]))
    assert yaw == pytest.approx(fraction * true, rel=0.02)


def test_iterations_are_checked_and_default_by_network() -> None:
    assert _predictor(None).pose_iterations == DEFAULT_POSE_ITERATIONS
    with pytest.raises(CylsfmError, match=">= 0"):
        _predictor(-1)
    one_pass = _HalfCompassNet()
    one_pass.antisymmetric = False  # the paper's network: its slot prior would be added at every pass
    cfg = preset("default")
    models = LoadedModels(_FlatDisp(), one_pass, cfg, 0, Path("stub"))  # type: ignore[arg-type]
    assert Predictor(models).pose_iterations == 0
    with pytest.raises(CylsfmError, match="frame pairs"):
        Predictor(models, pose_iterations=2)


def test_standing_camera_stays_still_through_the_passes(tmp_path: Path) -> None:
    """The default recipe's pair network, untrained: identical frames give zero motion in every pass."""
    predictor = Predictor.from_checkpoint(untrained_checkpoint(tmp_path, W, H), "cpu")
    assert predictor.pose_iterations == DEFAULT_POSE_ITERATIONS
    tgt = _panorama()
    pose = predictor.poses(tgt, tgt[:, None].repeat(1, 2, 1, 1, 1), CylindricalCamera.full(W, H))
    torch.testing.assert_close(pose, torch.eye(4, dtype=pose.dtype).expand_as(pose), atol=1e-5, rtol=0)
