"""The pose network reading turned frames: ``Predictor.poses(roll=)`` turns its poses back."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch import nn

from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera
from cylsfm.model import Predictor
from cylsfm.model.build import LoadedModels
from cylsfm.model.config import preset
from helpers import PoseStub

W, H = 128, 32


class _HeadingNet(PoseStub):
    """A pose network that reads the direction of travel from the brightest column of the target (its
    azimuth ``theta``) and reports ``gain * theta``: right when the motion is straight ahead (azimuth 0),
    pulled towards straight ahead otherwise (``gain < 1``), like a network trained on forward-facing rides."""

    pairs = False  # a one-pass network: Predictor makes no further passes with it

    def __init__(self, gain: float) -> None:
        super().__init__()
        self.gain = gain

    def forward(self, target: torch.Tensor, sources: torch.Tensor):
        w = target.shape[-1]
        col = target[:, 0].mean(1).argmax(-1).double()  # [B]
        heading = self.gain * (col - w / 2) * 2 * math.pi / w
        s = sources.shape[1]
        offsets = torch.tensor([*range(-(s // 2), 0), *range(1, s - s // 2 + 1)], dtype=torch.float64)
        vec = torch.zeros(target.shape[0], s, 6, dtype=torch.float64)
        # the centre of source o in the target's frame is o * (sin a, 0, cos a); no rotation: t = -centre
        vec[..., 0] = -offsets * torch.sin(heading)[:, None]
        vec[..., 2] = -offsets * torch.cos(heading)[:, None]
        vec[..., 3] = 0.01 * torch.sin(heading)[:, None]  # and a tilt about the direction of travel
        vec[..., 5] = 0.01 * torch.cos(heading)[:, None]
        return vec.float(), None


def _predictor(gain: float, fov: float = 360.0) -> Predictor:
    cfg = preset("default")
    cfg.data.width, cfg.data.height, cfg.data.fov = W, H, fov
    return Predictor(LoadedModels(nn.Identity(), _HeadingNet(gain), cfg, 0, Path("stub")))  # type: ignore[arg-type]


def _window(column: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A window whose target is dark but for one bright column (the direction of travel)."""
    tgt = torch.full((1, 3, H, W), 0.1)
    tgt[..., column] = 1.0
    return tgt, tgt[:, None].repeat(1, 2, 1, 1, 1)


def _heading(pose: torch.Tensor) -> float:
    """Azimuth of the travel from the source before the target to the one after it."""
    c = [-(p[:3, :3].T @ p[:3, 3]) for p in pose[0]]
    d = c[1] - c[0]
    return math.atan2(float(d[0]), float(d[2]))


@pytest.mark.parametrize("column", [64, 80, 100, 10, 127])
def test_turned_frames_give_poses_in_the_frames_own_camera(column):
    cam = CylindricalCamera.full(W, H)
    truth = (column - W / 2) * 2 * math.pi / W
    tgt, src = _window(column)
    exact, pulled = _predictor(1.0), _predictor(0.5)
    # a network that reads every direction gives the same poses however the frames are turned
    for roll in (1, 37, 64, 127):
        turned = exact.poses(tgt, src, cam, roll=roll)
        torch.testing.assert_close(turned, exact.poses(tgt, src, cam), atol=1e-6, rtol=0)
    # one pulled towards straight ahead is right once the motion is turned straight ahead
    assert _heading(pulled.poses(tgt, src, cam)) == pytest.approx(0.5 * truth, abs=1e-6)
    ahead = (64 - column) % W
    assert _heading(pulled.poses(tgt, src, cam, roll=ahead)) == pytest.approx(truth, abs=1e-6)


def test_turning_needs_a_full_panorama_model():
    cam = CylindricalCamera.full(W, H)
    tgt, src = _window(70)
    with pytest.raises(CylsfmError, match="full panoramas"):
        _predictor(1.0, fov=180.0).poses(tgt, src, cam, roll=3)
