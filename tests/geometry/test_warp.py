import math

import pytest
import torch

from cylsfm import CylindricalCamera, PinholeCamera, inverse_warp
from cylsfm.data.synth.room import make_pose
from cylsfm.geometry import relative_pose, sample_image


def _mean_abs(a, b, mask):
    m = mask.float()
    return float(((a - b).abs() * m).sum() / (m.sum() * a.shape[1]))


def test_seam_sample_blends_last_and_first_column():
    w, h = 8, 4
    img = torch.arange(w, dtype=torch.float64).view(1, 1, 1, w).expand(1, 1, h, w).contiguous()
    cases = {
        w - 0.5: 0.5 * (w - 1) + 0.5 * 0,  # half way across the seam
        w - 0.75: 0.75 * (w - 1) + 0.25 * 0,
        -0.25: 0.25 * (w - 1) + 0.75 * 0,  # negative u wraps too
        w + 1.5: 0.5 * 1 + 0.5 * 2,  # u beyond W is the next turn
        3.25: 3.25,
    }
    for u, expected in cases.items():
        uv = torch.tensor([u, 1.0], dtype=torch.float64).view(1, 2, 1, 1)
        out, valid = sample_image(img, uv, wrap=True)
        assert valid.all()
        assert out.item() == pytest.approx(expected), u
    # without wrap the same sample is outside the image
    out, valid = sample_image(
        img, torch.tensor([w - 0.5, 1.0], dtype=torch.float64).view(1, 2, 1, 1), wrap=False
    )
    assert not valid.any() and out.item() == 0


def test_vertical_out_of_range_is_invalid():
    img = torch.rand(1, 3, 4, 8)
    for v, ok in ((-0.01, False), (0.0, True), (3.0, True), (3.01, False)):
        _, valid = sample_image(img, torch.tensor([2.0, v]).view(1, 2, 1, 1), wrap=True)
        assert bool(valid.item()) is ok


def test_identity_warp_reproduces_the_image():
    cam = CylindricalCamera.full(64, 16)
    img = torch.rand(2, 3, 16, 64)
    depth = torch.rand(2, 1, 16, 64) * 10 + 1
    warped, valid = inverse_warp(img, depth, torch.eye(4).expand(2, 4, 4), cam)
    assert valid.all()
    assert torch.allclose(warped, img, atol=1e-4)


def test_pure_yaw_rotation_is_a_column_shift_across_the_seam():
    """Rotating a full panorama about the vertical axis by k pixels rolls it by k columns, seam included."""
    w, h = 64, 16
    cam = CylindricalCamera.full(w, h)
    img = torch.rand(1, 3, h, w)
    depth = torch.rand(1, 1, h, w) * 10 + 1

    def yaw(k: float) -> torch.Tensor:
        # a target point at azimuth theta is at theta + a in the source camera
        a = 2 * math.pi * k / w
        T = torch.eye(4)
        T[:3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        return T.unsqueeze(0)

    warped, valid = inverse_warp(img, depth, yaw(5), cam)
    assert valid.all()
    assert torch.allclose(warped, torch.roll(img, -5, dims=-1), atol=1e-4)
    # half a pixel more: every sample blends two columns, the one of target column 58 blends 63 and 0
    warped, valid = inverse_warp(img, depth, yaw(5.5), cam)
    assert valid.all()
    expected = 0.5 * (torch.roll(img, -5, dims=-1) + torch.roll(img, -6, dims=-1))
    assert torch.allclose(warped, expected, atol=1e-4)
    assert torch.allclose(warped[..., 58], 0.5 * (img[..., 63] + img[..., 0]), atol=1e-4)
    # without wrap exactly that sample, which falls between the last and the first column, is invalid
    _, valid_nowrap = inverse_warp(img, depth, yaw(5.5), cam, wrap=False)
    assert not valid_nowrap[..., 58].any()
    assert valid_nowrap[..., :58].all() and valid_nowrap[..., 59:].all()


@pytest.mark.parametrize("camera", [CylindricalCamera.full(256, 64), PinholeCamera.from_fov(128, 64, 100)])
def test_ground_truth_warp_explains_the_target(room, camera):
    """Warping a real second view with the true depth and pose reproduces the target view."""
    c2w_tgt = make_pose(0.2, 0.1, 0.3, yaw_deg=15)
    c2w_src = make_pose(0.45, 0.15, 1.05, yaw_deg=27, pitch_deg=3)
    tgt, depth = room(camera, c2w_tgt)
    src, _ = room(camera, c2w_src)
    T = relative_pose(c2w_tgt, c2w_src).float().unsqueeze(0)
    warped, valid = inverse_warp(src, depth, T, camera)
    assert valid.float().mean() > (0.9 if camera.wraps else 0.5)
    err_warp = _mean_abs(warped, tgt, valid)
    err_none = _mean_abs(src, tgt, valid)
    assert err_warp * 5 < err_none, (err_warp, err_none)
    # a wrong pose (no motion) explains the target much worse than the true one
    wrong, valid_w = inverse_warp(src, depth, torch.eye(4).unsqueeze(0), camera)
    assert _mean_abs(wrong, tgt, valid_w) > 3 * err_warp


def test_warp_gradients_reach_depth_and_pose(room):
    cam = CylindricalCamera.full(128, 32)
    tgt, depth = room(cam, make_pose(0, 0, 0))
    src, _ = room(cam, make_pose(0.1, 0, 0.4))
    T = relative_pose(make_pose(0, 0, 0), make_pose(0.1, 0, 0.4)).float().unsqueeze(0).requires_grad_(True)
    d = depth.clone().requires_grad_(True)
    warped, valid = inverse_warp(src, d, T, cam)
    ((warped - tgt).abs() * valid).mean().backward()
    assert torch.isfinite(d.grad).all() and d.grad.abs().sum() > 0
    assert torch.isfinite(T.grad).all() and T.grad.abs().sum() > 0


def test_bad_arguments_are_refused():
    cam = CylindricalCamera.full(64, 16)
    with pytest.raises(ValueError, match="wrap=True"):
        inverse_warp(
            torch.rand(1, 3, 16, 64), torch.ones(1, 1, 16, 64), torch.eye(4)[None], cam.crop(180), wrap=True
        )
    with pytest.raises(ValueError, match="T_tgt_to_src"):
        inverse_warp(torch.rand(1, 3, 16, 64), torch.ones(1, 1, 16, 64), torch.eye(4), cam)
    with pytest.raises(ValueError, match="differ"):
        inverse_warp(torch.rand(1, 3, 16, 64), torch.ones(1, 1, 16, 32), torch.eye(4)[None], cam)
