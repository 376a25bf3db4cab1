"""Resampling equirectangular, cylindrical and pinhole images into a cylindrical camera."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from cylsfm.data.convert import plan_resampling, to_cylinder
from cylsfm.data.synth import StreetScene, SynthConfig, make_camera, render_frame
from cylsfm.errors import InputError
from cylsfm.geometry import CylindricalCamera, EquirectangularCamera, PinholeCamera


def _t(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255


@pytest.fixture(scope="module")
def street():
    """Frame 1 of a street rendered as a 512x256 equirectangular and as a 256x64 cylindrical panorama."""
    scene = StreetScene.generate(3, SynthConfig(frames=3))
    eq = make_camera("equirect", 512, 256)
    cyl = make_camera("cylindrical", 256, 64)
    return eq, _t(render_frame(scene, 1, eq)[0]), cyl, _t(render_frame(scene, 1, cyl)[0])


def test_equirect_render_converts_to_the_cylindrical_render(street):
    eq, img_eq, cyl, img_cyl = street
    out, mask = to_cylinder(img_eq, eq, cyl, return_mask=True)
    assert out.shape == img_cyl.shape and mask.shape == (1, 1, 64, 256) and bool(mask.all())
    err = float((out - img_cyl).abs().mean())
    assert err < 0.03, err
    # a deliberately wrong conversion is far worse: the cylinder turned by 4 columns, or the equirect
    # image read 3 rows off
    turned = float((to_cylinder(img_eq, eq, replace(cyl, cx=cyl.cx + 4)) - img_cyl).abs().mean())
    lifted = float((to_cylinder(img_eq, replace(eq, cy=eq.cy + 3), cyl) - img_cyl).abs().mean())
    assert turned > 4 * err and lifted > 3 * err, (err, turned, lifted)


def test_same_camera_is_the_identity_and_batches_work(street):
    _, _, cyl, img_cyl = street
    batch = torch.cat([img_cyl, img_cyl.flip(-1)])
    out = to_cylinder(batch, cyl, cyl)
    torch.testing.assert_close(out, batch, atol=1e-5, rtol=0)
    assert to_cylinder(batch.double(), cyl, cyl).dtype == torch.float64


def test_known_point_lands_where_the_projections_say():
    """The point p = (2, 1, 2) of docs/conventions.md: an equirect blob at its (x_e, y_e) ends up at (225, 67.18)."""
    src = EquirectangularCamera.full(720, 360)
    dst = CylindricalCamera.full(360, 100, 1.0)
    xe = 720 * (math.radians(45) / (2 * math.pi) + 0.5) - 0.5
    ye = 360 * (math.asin(1 / 3) / math.pi + 0.5) - 0.5
    assert xe == pytest.approx(449.5) and ye == pytest.approx(218.44, abs=0.01)
    p = torch.tensor([2.0, 1.0, 2.0], dtype=torch.float64).view(1, 3, 1, 1)
    torch.testing.assert_close(src.project(p).flatten(), torch.tensor([xe, ye], dtype=torch.float64))
    v, u = torch.meshgrid(torch.arange(360.0), torch.arange(720.0), indexing="ij")
    blob = torch.exp(-((u - xe) ** 2 + (v - ye) ** 2) / (2 * 2.0**2))[None, None]
    out = to_cylinder(blob, src, dst)[0, 0]
    vv, uu = torch.meshgrid(torch.arange(100.0), torch.arange(360.0), indexing="ij")
    w = out / out.sum()
    assert float((w * uu).sum()) == pytest.approx(225.0, abs=0.1)
    assert float((w * vv).sum()) == pytest.approx(67.18, abs=0.15)


def test_wraps_across_the_seam():
    """A full equirectangular source is sampled across its seam: column 0 of a full cylinder looks back."""
    src = EquirectangularCamera.full(64, 32)
    dst = CylindricalCamera.full(32, 8, 0.5)
    img = torch.zeros(1, 1, 32, 64)
    img[..., 0] = 1.0
    img[..., -1] = 1.0  # a bright band straddling the seam (straight back)
    out, mask = to_cylinder(img, src, dst, supersample=1, return_mask=True)
    assert bool(mask.all())
    assert float(out[..., 0].min()) == pytest.approx(1.0)  # theta = -pi sits exactly on the seam
    assert float(out[..., 1:-1].max()) < 0.5
    # without wrapping the seam column has no left neighbour and becomes invalid
    _, mask = to_cylinder(img, src, dst, wrap=False, supersample=1, return_mask=True)
    assert not bool(mask[..., 0].any()) and bool(mask[..., 1:].all())
    with pytest.raises(InputError, match="full turn"):
        to_cylinder(img, replace(src, fx=20.0), dst, wrap=True)


def test_pinhole_source_leaves_the_rest_black_and_masked():
    src = PinholeCamera.from_fov(64, 48, 90.0)
    dst = CylindricalCamera.full(128, 32, 0.5)
    img = torch.full((1, 3, 48, 64), 0.8)
    out, mask = to_cylinder(img, src, dst, return_mask=True)
    theta = (torch.arange(128.0) - float(dst.cx)) / float(dst.fx)
    inside = theta.abs() < math.radians(43)
    outside = theta.abs() > math.radians(46)
    assert bool(mask[0, 0][:, inside].all()) and not bool(mask[0, 0][:, outside].any())
    torch.testing.assert_close(out[0][:, :, inside], torch.full_like(out[0][:, :, inside], 0.8))
    assert float(out[0][:, :, outside].abs().max()) == 0.0  # behind the camera too (z <= 0)


def test_large_downsizing_is_antialiased():
    """5760x2880 white noise into a 512x128 cylinder averages ~100 source pixels a pixel."""
    src = EquirectangularCamera.full(5760, 2880)
    dst = CylindricalCamera.full(512, 128)
    (sx, sy), (kx, ky) = plan_resampling(src, dst)
    assert (sx, sy) == (4, 4) and kx >= 2 and ky >= 2
    g = torch.Generator().manual_seed(0)
    noise = torch.rand(1, 1, 2880, 5760, generator=g)
    out = to_cylinder(noise, src, dst)
    naive = to_cylinder(noise, src, dst, supersample=1)
    assert float(out.mean()) == pytest.approx(0.5, abs=0.01)
    assert float(out.std()) < 0.05 < 0.15 < float(naive.std())
    assert plan_resampling(dst, dst) == ((1, 1), (1, 1))  # same size: plain bilinear


def test_depth_to_camera_gives_the_other_cameras_depth(room):
    from cylsfm.data.convert import depth_to_camera
    from cylsfm.data.synth.room import make_pose

    c2w = make_pose(0.2, 0.1, -0.3, yaw_deg=15.0)
    cyl, eq = CylindricalCamera.full(512, 128), EquirectangularCamera.full(256, 128)
    _, d_cyl = room(cyl, c2w, supersample=1)
    _, d_eq = room(eq, c2w, supersample=1)
    got = depth_to_camera(d_cyl, cyl, eq)[0, 0]
    truth = d_eq[0, 0]
    rows = torch.arange(128).float()
    band = (rows - 63.5).abs() * math.pi / 128 < math.radians(44)  # the cylinder's band: +-45 degrees
    assert bool((got[:8] == 0).all()) and bool((got[-8:] == 0).all())  # the poles: not seen
    rel = ((got - truth).abs() / truth)[band]
    assert float(rel.median()) < 0.01 and float((rel < 0.05).float().mean()) > 0.95
