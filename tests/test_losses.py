import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from cylsfm.data.synth.room import make_pose
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


@pytest.mark.parametrize("min_reprojection", [False, True])
@pytest.mark.parametrize("automask", [False, True])
def test_a_static_scene_is_auto_masked_whatever_the_pose_says(room, automask, min_reprojection):
    """The camera stood still (every view is the same picture) while the pose says it moved and turned.

    Warping with that pose misaligns the views; auto-masking sees that not warping at all explains every
    pixel better and drops them all (nothing to pay); without it the wrong motion is paid for.
    """
    cam = CylindricalCamera.full(128, 32)
    target, depth = room(cam, make_pose(0.0, 0.0, 0.0))
    sources = target.unsqueeze(1).repeat(1, 2, 1, 1, 1)
    moved = [make_pose(0.05, 0.0, -0.35, 8), make_pose(-0.05, 0.02, 0.4, -6)]
    poses = torch.stack([relative_pose(make_pose(0.0, 0.0, 0.0), p).float() for p in moved])[None]
    disp = image_pyramid(1 / depth, [(32 // 2**s, 128 // 2**s) for s in range(4)])
    cfg = LossConfig(smooth_weight=0, ssim_weight=0.85, min_reprojection=min_reprojection, automask=automask)
    torch.manual_seed(0)  # the tie-breaking noise of minimum reprojection with auto-masking
    out = view_synthesis_loss(target, sources, disp, poses, cam, cfg)
    photometric = out.terms["photometric"].item()
    if automask:
        # no pixel is kept (without minimum reprojection exactly none; with it, at most pixels whose
        # error is below the 1e-5 tie-breaking noise)
        assert photometric == pytest.approx(0, abs=1e-5)
    else:
        assert photometric > 0.05
    assert out.total.item() == pytest.approx(photometric, abs=1e-7)


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


def _windows(a: np.ndarray, wrap: bool) -> np.ndarray:
    """The 3x3 neighbourhood of every pixel of ``a [H,W]`` -> ``[H,W,9]``: rows reflected at the top and
    bottom, columns wrapped around (``wrap``) or reflected."""
    h, w = a.shape

    def reflect(i: int, n: int) -> int:
        return -i if i < 0 else 2 * (n - 1) - i if i >= n else i

    out = np.empty((h, w, 9))
    for i in range(h):
        for j in range(w):
            out[i, j] = [
                a[reflect(i + di, h), (j + dj) % w if wrap else reflect(j + dj, w)]
                for di in (-1, 0, 1)
                for dj in (-1, 0, 1)
            ]
    return out


C1, C2 = 0.01**2, 0.03**2


def _ssim_error_reference(x: np.ndarray, y: np.ndarray, wrap: bool) -> np.ndarray:
    """(1 - SSIM) / 2 of ``[C,H,W]`` images over 3x3 windows, clipped to [0, 1], averaged over channels."""
    out = []
    for xc, yc in zip(x, y, strict=True):
        wx, wy = _windows(xc, wrap), _windows(yc, wrap)
        mx, my = wx.mean(-1), wy.mean(-1)
        vx, vy = wx.var(-1), wy.var(-1)
        cov = ((wx - mx[..., None]) * (wy - my[..., None])).mean(-1)
        ssim = (2 * mx * my + C1) * (2 * cov + C2) / ((mx**2 + my**2 + C1) * (vx + vy + C2))
        out.append(np.clip((1 - ssim) / 2, 0, 1))
    return np.mean(out, axis=0)


@pytest.mark.parametrize("wrap", [False, True])
def test_ssim_error_matches_its_closed_form(wrap):
    gen = torch.Generator().manual_seed(3)
    x = torch.rand(2, 3, 5, 7, generator=gen, dtype=torch.float64)
    y = torch.rand(2, 3, 5, 7, generator=gen, dtype=torch.float64)
    assert ssim_error(x, x, wrap=wrap).abs().max() < 1e-12
    got = ssim_error(x, y, wrap=wrap)
    assert got.shape == (2, 1, 5, 7)
    for b in range(2):
        ref = _ssim_error_reference(x[b].numpy(), y[b].numpy(), wrap)
        np.testing.assert_allclose(got[b, 0].numpy(), ref, rtol=0, atol=1e-12)
    # The negative: window means m and 1 - m, equal variances v, covariance -v, so per channel
    # SSIM = (2 m (1 - m) + C1) (C2 - 2 v) / ((m^2 + (1 - m)^2 + C1) (2 v + C2)).
    expected = []
    for c in range(3):
        win = _windows(x[0, c].numpy(), wrap)
        m, v = win.mean(-1), win.var(-1)
        ssim = (2 * m * (1 - m) + C1) * (C2 - 2 * v) / ((m**2 + (1 - m) ** 2 + C1) * (2 * v + C2))
        expected.append(np.clip((1 - ssim) / 2, 0, 1))
    np.testing.assert_allclose(ssim_error(x, 1 - x, wrap)[0, 0].numpy(), np.mean(expected, 0), atol=1e-12)
    # Constant pictures 0.2 and 0.8: only the means differ.
    flat = ssim_error(torch.full((1, 1, 4, 4), 0.2), torch.full((1, 1, 4, 4), 0.8), wrap)
    ssim = (2 * 0.2 * 0.8 + C1) / (0.2**2 + 0.8**2 + C1)
    torch.testing.assert_close(flat, torch.full_like(flat, (1 - ssim) / 2))


def test_photometric_error_mixes_ssim_and_l1():
    gen = torch.Generator().manual_seed(4)
    x, y = torch.rand(2, 3, 6, 8, generator=gen), torch.rand(2, 3, 6, 8, generator=gen)
    l1 = (x - y).abs().mean(1, keepdim=True)
    torch.testing.assert_close(photometric_error(x, y), l1)
    err = photometric_error(x, x + 0.1)
    torch.testing.assert_close(err, torch.full_like(err, 0.1))
    for wrap in (False, True):
        mixed = photometric_error(x, y, ssim_weight=0.85, wrap=wrap)
        torch.testing.assert_close(mixed, 0.85 * ssim_error(x, y, wrap) + 0.15 * l1)


def _image_aware_reference(disp: np.ndarray, image: np.ndarray, wrap: bool, order: int) -> float:
    """Image-aware smoothness of ``disp [B,1,H,W]`` and ``image [B,C,H,W]``, written out pixel by pixel.

    Order 1: mean over x-differences of ``|dD/dx| exp(-mean_c |dI/dx|)`` plus the same along y.
    Order 2: mean over rows ``0..H-3`` and columns ``0..W-3`` (every column with wrap) of
    ``exp(-mean_c |I_xx + I_yy|) (|D_xx| + |D_xy| + |D_yy|)``, forward differences from each pixel.
    """
    b, _, h, w = disp.shape
    col = (lambda j: j % w) if wrap else (lambda j: j)
    n_x = w if wrap else w - 1
    if order == 1:
        sx = sum(
            abs(disp[k, 0, i, col(j + 1)] - disp[k, 0, i, j])
            * math.exp(-np.mean(np.abs(image[k, :, i, col(j + 1)] - image[k, :, i, j])))
            for k in range(b)
            for i in range(h)
            for j in range(n_x)
        )
        sy = sum(
            abs(disp[k, 0, i + 1, j] - disp[k, 0, i, j])
            * math.exp(-np.mean(np.abs(image[k, :, i + 1, j] - image[k, :, i, j])))
            for k in range(b)
            for i in range(h - 1)
            for j in range(w)
        )
        return sx / (b * h * n_x) + sy / (b * (h - 1) * w)

    def xx(a, i, j):
        return a[..., i, col(j + 2)] - 2 * a[..., i, col(j + 1)] + a[..., i, j]

    def yy(a, i, j):
        return a[..., i + 2, j] - 2 * a[..., i + 1, j] + a[..., i, j]

    def xy(a, i, j):
        return a[..., i + 1, col(j + 1)] - a[..., i + 1, j] - a[..., i, col(j + 1)] + a[..., i, j]

    n_x = w if wrap else w - 2
    total = 0.0
    for k in range(b):
        for i in range(h - 2):
            for j in range(n_x):
                weight = math.exp(-np.mean(np.abs(xx(image[k], i, j) + yy(image[k], i, j))))
                d = disp[k, 0]
                total += weight * (abs(xx(d, i, j)) + abs(xy(d, i, j)) + abs(yy(d, i, j)))
    return total / (b * (h - 2) * n_x)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("wrap", [False, True])
def test_image_aware_smoothness_matches_its_closed_form(order, wrap):
    gen = torch.Generator().manual_seed(5)
    disp = torch.rand(2, 1, 5, 7, generator=gen, dtype=torch.float64) + 0.1
    image = torch.rand(2, 3, 5, 7, generator=gen, dtype=torch.float64)
    got = image_aware_smoothness(disp, image, wrap=wrap, order=order)
    assert got.item() == pytest.approx(
        _image_aware_reference(disp.numpy(), image.numpy(), wrap, order), rel=1e-12
    )
    normalized = image_aware_smoothness(disp, image, wrap=wrap, order=order, mean_normalize=True)
    scaled = (disp / disp.mean(dim=(2, 3), keepdim=True)).numpy()
    assert normalized.item() == pytest.approx(
        _image_aware_reference(scaled, image.numpy(), wrap, order), rel=1e-12
    )


def test_image_aware_smoothness_by_hand():
    # Order 1: a disparity step of 1 where the image steps by 0.5 (at column 2, and at the seam with wrap).
    disp = torch.tensor([0.0, 0.0, 1.0, 1.0]).expand(1, 1, 2, 4)
    image = torch.tensor([0.5, 0.5, 1.0, 1.0]).expand(1, 3, 2, 4)
    step = math.exp(-0.5)
    assert image_aware_smoothness(disp, image, wrap=False).item() == pytest.approx(step / 3)  # 1 of 3 columns
    assert image_aware_smoothness(disp, image, wrap=True).item() == pytest.approx(step / 2)  # 2 of 4
    # Order 2: D = (j + 1)^2 has D_xx = 2 and no other curvature; the image 0.1 (j + 1)^2 has Laplacian 0.2.
    j = torch.arange(1.0, 6.0)
    disp = (j**2).expand(1, 1, 3, 5)
    image = (0.1 * j**2).expand(1, 3, 3, 5)
    assert image_aware_smoothness(disp, image, False, order=2).item() == pytest.approx(2 * math.exp(-0.2))
    assert image_aware_smoothness(disp, torch.zeros_like(image), False, order=2).item() == pytest.approx(2)
    # divided by the mean disparity (1 + 4 + 9 + 16 + 25) / 5 = 11 first
    normalized = image_aware_smoothness(disp, image, False, order=2, mean_normalize=True)
    assert normalized.item() == pytest.approx(2 / 11 * math.exp(-0.2))
    assert image_aware_smoothness(7 * disp, image, False, 2, mean_normalize=True).item() == pytest.approx(
        normalized.item()
    )


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


def test_explainability_weights_the_photometric_term_and_adds_its_cross_entropy():
    b, h, w = 1, 32, 128
    cam = CylindricalCamera.full(w, h)
    gen = torch.Generator().manual_seed(6)
    target, sources = torch.rand(b, 3, h, w, generator=gen), torch.rand(b, 2, 3, h, w, generator=gen)
    args = (target, sources, _pyramid_disp(b, h, w, 0.3), torch.eye(4).expand(b, 2, 4, 4), cam)
    masks = [torch.rand(b, 2, h // 2**s, w // 2**s, generator=gen) * 0.9 + 0.05 for s in range(4)]
    off = view_synthesis_loss(*args, LossConfig(smooth_weight=0), explainability=masks)
    on = view_synthesis_loss(*args, LossConfig(smooth_weight=0, explain_weight=0.2), explainability=masks)
    # lambda_e * S * (cross-entropy towards 1 = mean of -log E), summed over scales
    expected = sum(0.2 * 2 * float(-torch.log(m).mean()) for m in masks)
    assert off.terms["explain"].item() == 0
    assert on.terms["explain"].item() == pytest.approx(expected, rel=1e-5)
    assert (on.total - off.total).item() == pytest.approx(expected, rel=1e-5)
    assert on.terms["photometric"].item() == off.terms["photometric"].item()
    assert explainability_loss(torch.full((1, 2, 4, 4), 0.5)).item() == pytest.approx(math.log(2), rel=1e-6)
    assert explainability_loss(torch.ones(1, 2, 4, 4)).item() == 0
    # eq. 3: each source's photometric error is weighted by its mask (one scale: the mean scales with E)
    one = (target, sources, [torch.full((b, 1, h, w), 0.3)], torch.eye(4).expand(b, 2, 4, 4), cam)
    full = view_synthesis_loss(*one, explainability=[torch.ones(b, 2, h, w)]).terms["photometric"]
    mask = torch.tensor([0.25, 0.75]).view(1, 2, 1, 1).expand(b, 2, h, w)
    half = view_synthesis_loss(*one, explainability=[mask]).terms["photometric"]
    per_source = [photometric_error(target, sources[:, k]).mean() for k in range(2)]
    assert full.item() == pytest.approx(sum(per_source).item(), rel=1e-5)
    assert half.item() == pytest.approx((0.25 * per_source[0] + 0.75 * per_source[1]).item(), rel=1e-5)


def _quadratic_pyramid(b, h, w, c):
    """Disparities ``c (j + 1)^2`` along the width at every scale: second x-derivative ``2 c``, nothing else."""
    return [
        (c * torch.arange(1.0, w // 2**s + 1) ** 2).expand(b, 1, h // 2**s, w // 2**s).contiguous()
        for s in range(4)
    ]


@pytest.mark.parametrize("decay", [True, False])
def test_smoothness_weights_per_scale(decay):
    """``smooth_scale_decay`` divides scale s's smoothness weight by 2^s; off, every scale weighs the same."""
    b, h, w = 1, 32, 128
    cam = CylindricalCamera.full(w, h)
    target = torch.full((b, 3, h, w), 0.5)  # flat: the image-aware weights are all 1
    args = (target, target.unsqueeze(1).repeat(1, 2, 1, 1, 1))
    poses, c = torch.eye(4).expand(b, 2, 4, 4), 1e-4
    scale = [1 / 2**s if decay else 1.0 for s in range(4)]
    widths = [w // 2**s for s in range(4)]

    def smooth(**kw):
        cfg = LossConfig(smooth_scale_decay=decay, **kw)
        return view_synthesis_loss(*args, _quadratic_pyramid(b, h, w, c), poses, cam, cfg, wrap=False).terms[
            "smooth"
        ]

    # eq. 4: |D_xx| = 2c everywhere, the other three terms vanish
    assert smooth(smooth_weight=2.0).item() == pytest.approx(2.0 * sum(2 * c * k for k in scale), rel=1e-4)
    # first order: |dD/dx| = c (2j + 3) for j = 0 .. W_s - 2, whose mean is c (W_s + 1)
    image_aware = smooth(smooth_weight=0, image_smooth_weight=0.5)
    expected = 0.5 * sum(c * (ws + 1) * k for ws, k in zip(widths, scale, strict=True))
    assert image_aware.item() == pytest.approx(expected, rel=1e-4)


def test_smooth_mean_normalize_makes_the_image_aware_term_scale_free():
    """Divided by its mean c (W + 1)(2W + 1) / 6, the first-order term of c (j + 1)^2 is 6 / (2W + 1)."""
    b, h, w = 1, 32, 128
    cam = CylindricalCamera.full(w, h)
    target = torch.full((b, 3, h, w), 0.5)
    args = (target, target.unsqueeze(1).repeat(1, 2, 1, 1, 1))
    poses = torch.eye(4).expand(b, 2, 4, 4)
    cfg = LossConfig(smooth_weight=0, image_smooth_weight=0.5, smooth_mean_normalize=True)
    expected = 0.5 * sum(6 / (2 * (w // 2**s) + 1) / 2**s for s in range(4))
    for c in (1e-4, 1e-3):
        disp = _quadratic_pyramid(b, h, w, c)
        out = view_synthesis_loss(*args, disp, poses, cam, cfg, wrap=False).terms["smooth"]
        assert out.item() == pytest.approx(expected, rel=1e-4)
        plain = replace(cfg, smooth_mean_normalize=False)
        out = view_synthesis_loss(*args, disp, poses, cam, plain, wrap=False).terms["smooth"]
        assert out.item() == pytest.approx(0.5 * sum(c * (w // 2**s + 1) / 2**s for s in range(4)), rel=1e-4)


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
