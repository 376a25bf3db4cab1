"""``Predictor.ride_poses``: the windows of a ride with each pair of frames read once by the first pass,
against ``Predictor.poses`` of the same windows (the plain path)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera
from cylsfm.model import Predictor, build_models, preset
from cylsfm.model.build import LoadedModels

W, H = 128, 32


def _predictor(seq_length: int = 3, antisymmetric: bool = True) -> Predictor:
    cfg = preset("default")
    cfg.data.width, cfg.data.height, cfg.data.seq_length = W, H, seq_length
    cfg.model.antisymmetric = antisymmetric
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    return Predictor(LoadedModels(disp.eval(), pose.eval(), cfg, 0, Path("untrained")), amp=False)


def _frames(n: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    coarse = torch.rand(n, 3, H // 4, W // 4, generator=g)
    return torch.nn.functional.interpolate(coarse, size=(H, W), mode="bilinear", align_corners=False)


def _windows(frames: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    n = frames.shape[0]
    tgt = frames[k : n - k]
    src = torch.stack([frames[k + o : n - k + o] for o in range(-k, k + 1) if o], 1)
    return tgt, src


@pytest.mark.parametrize(("seq_length", "roll"), [(3, 0), (3, 5), (5, 0)])
def test_ride_poses_are_the_windows_poses(seq_length: int, roll: int) -> None:
    p = _predictor(seq_length)
    k = (seq_length - 1) // 2
    frames, cam = _frames(8), CylindricalCamera.full(W, H)
    tgt, src = _windows(frames, k)
    plain = p.poses(tgt, src, cam, roll)
    shared = p.ride_poses(frames, cam, roll)
    assert shared.shape == plain.shape == (8 - 2 * k, 2 * k, 4, 4)
    torch.testing.assert_close(shared, plain, atol=1e-5, rtol=1e-4)
    assert float((plain[..., :3, 3]).abs().max()) > 1e-4  # not trivially zero


def test_ride_poses_take_the_targets_depth() -> None:
    p = _predictor()
    frames, cam = _frames(6), CylindricalCamera.full(W, H)
    tgt, src = _windows(frames, 1)
    depth = 1.0 + torch.rand(4, 1, H, W, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(
        p.ride_poses(frames, cam, depth=depth), p.poses(tgt, src, cam, depth=depth), atol=1e-5, rtol=1e-4
    )
    with pytest.raises(CylsfmError, match="does not fit"):
        p.ride_poses(frames, cam, depth=depth[:3])


def test_a_one_pass_network_reads_each_window_whole() -> None:
    p = _predictor(antisymmetric=False)
    frames, cam = _frames(5), CylindricalCamera.full(W, H)
    torch.testing.assert_close(p.ride_poses(frames, cam), p.poses(*_windows(frames, 1), cam))


def test_ride_poses_refuse_too_few_frames_and_uncentred_windows() -> None:
    cam = CylindricalCamera.full(W, H)
    with pytest.raises(CylsfmError, match="at least 3 frames"):
        _predictor().ride_poses(_frames(2), cam)
    with pytest.raises(CylsfmError, match="centred"):
        _predictor(seq_length=4).ride_poses(_frames(6), cam)
