import math

import pytest
import torch

from conftest import make_pose
from cylsfm.geometry import CylindricalCamera, relative_pose, resize_image
from cylsfm.losses import (
    LossConfig,
    explainability_loss,
    image_aware_smoothness,
    image_pyramid,
    photometric_error,
    second_order_smoothness,
    second_order_terms,
    ssim_error,
    view_synthesis_loss,
)

VARIANTS = {
    "paper": LossConfig(),
    "headcam": LossConfig(smooth_weight=0, image_smooth_weight=0.2),
    "improved": LossConfig(ssim_weight=0.85, min_reprojection=True, automask=True, full_resolution=True),
}


def _pyramid_disp(b, h, w, value=None, seed=0):
    gen = torch.Generator().manual_seed(seed)
    out = []
    for s in range(4):
        shape = (b, 1, h // 2**s, w // 2**s)
        out.append(torch.full(shape, value) if value is not None else torch.rand(shape, generator=gen) + 0.1)
    return out


@pytest.mark.parametrize("name", list(VARIANTS))
def test_identical_views_cost_nothing(name):
    cfg = VARIANTS[name]
    b, h, w = 2, 32, 128
    cam = CylindricalCamera.full(w, h)
    target = torch.rand(b, 3, h, w)
    sources = target.unsqueeze(1).repeat(1, 2, 1, 1, 1)
    poses = torch.eye(4).expand(b, 2, 4, 4)
    masks = [torch.ones(b, 2, h // 2**s, w // 2**s) for s in range(4)]
    out = view_synthesis_loss(
        target, sources, _pyramid_disp(b, h, w, 0.3), poses, cam, cfg, explainability=masks
    )
    if name == "improved":
        # auto-masking drops every pixel (nothing moved), leaving nothing to pay for
        assert out.terms["photometric"].item() == pytest.approx(0, abs=1e-6)
    assert out.terms["photometric"].item() == pytest.approx(0, abs=1e-5)
    assert out.terms["smooth"].item() == pytest.approx(0, abs=1e-6)
    assert out.total.item() == pytest.approx(0, abs=1e-5)
    assert explainability_loss(masks[0]).item() == pytest.approx(0, abs=1e-6)
    assert explainability_loss(torch.full((1, 2, 4, 4), 0.5)).item() == pytest.approx(math.log(2), rel=1e-5)


def test_wrap_and_nowrap_smoothness_differ_only_at_the_seam():
    disp = torch.rand(2, 1, 16, 64)
    wrapped = second_order_terms(disp, wrap=True)
    plain = second_order_terms(disp, wrap=False)
    for a, p in zip(wrapped, plain, strict=True):
        assert a.shape[-1] == 64
        n = p.shape[-1]
        assert torch.equal(a[..., :n], p)  # identical away from the seam
        if n < 64:  # the x-derivatives have extra columns across the seam, and they carry information
            assert a[..., n:].abs().sum() > 0
    # A ramp in azimuth is perfectly smooth inside the image but jumps at the seam.
    ramp = torch.arange(64.0).view(1, 1, 1, 64).expand(1, 1, 16, 64)
    assert second_order_smoothness(ramp, wrap=False).item() == pytest.approx(0, abs=1e-6)
    dxx = second_order_terms(ramp, wrap=True)[0]
    assert dxx[..., :62].abs().max() == 0 and dxx[..., 62:].abs().min() > 0
    # A function periodic in azimuth is smooth across the seam: wrap sees no jump there.
    theta = torch.arange(64.0) * 2 * math.pi / 64
    periodic = torch.cos(theta).view(1, 1, 1, 64).expand(1, 1, 16, 64)
    seam = second_order_terms(periodic, wrap=True)[0][..., 62:].abs().max()
    inner = second_order_terms(periodic, wrap=True)[0][..., :62].abs().max()
    assert seam <= inner + 1e-6


def test_wrap_aware_ops_commute_with_a_roll():
    x, y = torch.rand(1, 3, 16, 64), torch.rand(1, 3, 16, 64)
    k = 7
    r = lambda t: torch.roll(t, k, dims=-1)  # noqa: E731
    assert torch.allclose(ssim_error(r(x), r(y), wrap=True), r(ssim_error(x, y, wrap=True)), atol=1e-6)
    assert not torch.allclose(ssim_error(r(x), r(y), wrap=False), r(ssim_error(x, y, wrap=False)), atol=1e-3)
    small = torch.rand(1, 1, 8, 16)
    up = resize_image(small, (16, 32), wrap=True)
    assert torch.allclose(
        resize_image(torch.roll(small, 3, -1), (16, 32), True), torch.roll(up, 6, -1), atol=1e-6
    )
    # away from the seam it is the ordinary bilinear upsampling
    plain = resize_image(small, (16, 32), wrap=False)
    assert torch.allclose(up[..., 2:-2], plain[..., 2:-2], atol=1e-6)
    for order in (1, 2):
        d = torch.rand(1, 1, 16, 64)
        a = image_aware_smoothness(r(d), r(x), wrap=True, order=order)
        assert a.item() == pytest.approx(
            image_aware_smoothness(d, x, wrap=True, order=order).item(), rel=1e-5
        )


def test_ssim_and_photometric_error_basics():
    x = torch.rand(2, 3, 16, 32)
    assert ssim_error(x, x, wrap=True).abs().max() < 1e-5
    assert ssim_error(x, 1 - x, wrap=True).mean() > 0.3
    err = photometric_error(x, x + 0.1)
    assert torch.allclose(err, torch.full_like(err, 0.1), atol=1e-6)


def test_image_aware_smoothness_relaxes_at_image_edges():
    disp = torch.zeros(1, 1, 16, 32)
    disp[..., 16:] = 1.0  # a depth edge at column 16 (and, wrapping, at the seam)
    flat = torch.full((1, 3, 16, 32), 0.5)
    edge = flat.clone()
    edge[..., 16:] = 1.0  # an image edge in the same place
    for order in (1, 2):
        plain = image_aware_smoothness(disp, flat, wrap=False, order=order)
        relaxed = image_aware_smoothness(disp, edge, wrap=False, order=order)
        assert relaxed < plain
        assert image_aware_smoothness(torch.ones_like(disp), edge, wrap=True, order=order) == 0


@pytest.mark.parametrize("name", list(VARIANTS))
def test_true_depth_and_pose_beat_wrong_ones(room, name):
    """On a rendered scene the loss prefers the true geometry, and its gradients reach depth and pose."""
    cam = CylindricalCamera.full(128, 32)
    poses_c2w = [make_pose(0.0, 0.0, 0.0), make_pose(0.05, 0.0, -0.35, 3), make_pose(-0.05, 0.02, 0.4, -4)]
    (tgt, depth), (s1, _), (s2, _) = (room(cam, p) for p in poses_c2w)
    sources = torch.stack((s1, s2), 1)
    poses = torch.stack([relative_pose(poses_c2w[0], p).float() for p in poses_c2w[1:]], 0).unsqueeze(0)
    disp_true = image_pyramid(1 / depth, [(32 // 2**s, 128 // 2**s) for s in range(4)])
    cfg = VARIANTS[name]
    good = view_synthesis_loss(tgt, sources, disp_true, poses, cam, cfg).terms["photometric"]
    flat = [torch.full_like(d, float((1 / depth).mean())) for d in disp_true]
    bad_depth = view_synthesis_loss(tgt, sources, flat, poses, cam, cfg).terms["photometric"]
    bad_pose = view_synthesis_loss(tgt, sources, disp_true, poses.flip(1), cam, cfg).terms["photometric"]
    assert good < 0.8 * bad_depth and good < 0.8 * bad_pose, (good, bad_depth, bad_pose)
    disp = [d.clone().requires_grad_(True) for d in flat]
    pose_var = poses.clone().requires_grad_(True)
    view_synthesis_loss(tgt, sources, disp, pose_var, cam, cfg).total.backward()
    assert all(torch.isfinite(d.grad).all() and d.grad.abs().sum() > 0 for d in disp)
    assert torch.isfinite(pose_var.grad).all() and pose_var.grad.abs().sum() > 0


def test_static_mask_hides_a_region_from_the_photometric_term():
    b, h, w = 1, 32, 128
    cam = CylindricalCamera.full(w, h)
    target = torch.rand(b, 3, h, w)
    sources = target.unsqueeze(1).repeat(1, 2, 1, 1, 1)
    spoiled = target.clone()
    spoiled[..., 24:, :] = 1 - spoiled[..., 24:, :]  # a "helmet" at the bottom differs between views
    mask = torch.ones(1, 1, h, w)
    mask[..., 24:, :] = 0
    args = (_pyramid_disp(b, h, w, 0.2), torch.eye(4).expand(b, 2, 4, 4), cam)
    cfg = LossConfig(smooth_weight=0)
    hidden = view_synthesis_loss(spoiled, sources, *args, cfg, static_mask=mask)
    shown = view_synthesis_loss(spoiled, sources, *args, cfg)
    # only the coarse scales' boundary row, blurred by area downsampling, still sees the spoiled region
    assert hidden.terms["photometric"] < 0.05 * shown.terms["photometric"]


def test_min_reprojection_picks_the_source_that_sees_the_pixel():
    b, h, w = 1, 32, 128
    cam = CylindricalCamera.full(w, h)
    target = torch.rand(b, 3, h, w)
    sources = torch.stack((target, torch.rand(b, 3, h, w)), 1)  # source 2 is garbage
    args = (_pyramid_disp(b, h, w, 0.2), torch.eye(4).expand(b, 2, 4, 4), cam)
    summed = view_synthesis_loss(target, sources, *args, LossConfig(smooth_weight=0))
    best = view_synthesis_loss(target, sources, *args, LossConfig(smooth_weight=0, min_reprojection=True))
    assert best.terms["photometric"].item() == pytest.approx(0, abs=1e-6)
    assert summed.terms["photometric"] > 0.1


def test_bad_configs_and_shapes_are_refused():
    with pytest.raises(ValueError, match="ssim_weight"):
        LossConfig(ssim_weight=2)
    with pytest.raises(ValueError, match="smooth_weight"):
        LossConfig(smooth_weight=-1)
    cam = CylindricalCamera.full(128, 32)
    with pytest.raises(ValueError, match="poses"):
        view_synthesis_loss(
            torch.rand(1, 3, 32, 128),
            torch.rand(1, 2, 3, 32, 128),
            _pyramid_disp(1, 32, 128),
            torch.eye(4)[None],
            cam,
        )
