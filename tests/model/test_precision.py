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
from cylsfm.model import Predictor
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


@pytest.fixture
def predictors(tmp_path: Path, monkeypatch) -> tuple[Predictor, Predictor]:
    monkeypatch.setattr(runtime, "native_bf16", lambda: True)
    ckpt = untrained_checkpoint(tmp_path, W, H)
    return Predictor.from_checkpoint(ckpt, "cpu", amp=False), Predictor.from_checkpoint(ckpt, "cpu")


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
