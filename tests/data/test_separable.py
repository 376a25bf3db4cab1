"""The separable box filter between full panoramas: weights that sum to one, the same result as dense
supersampling in the limit, rows outside a narrower source masked, batches and dtypes kept."""

from __future__ import annotations

import torch

from cylsfm.data.convert import Resampler, to_cylinder
from cylsfm.data.separable import SeparableMap, separable
from cylsfm.geometry import CylindricalCamera, EquirectangularCamera, PinholeCamera


def _smooth(h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, h // 8, w // 8, generator=g)
    return torch.nn.functional.interpolate(coarse, size=(h, w), mode="bicubic", align_corners=False)


def test_applies_only_between_full_panoramas_about_one_axis():
    cyl = CylindricalCamera.full(128, 32)
    assert separable(EquirectangularCamera.full(256, 128), cyl)
    assert separable(CylindricalCamera.full(256, 64, 0.5), cyl)
    assert not separable(PinholeCamera.from_fov(64, 48, 90.0), cyl)
    assert not separable(EquirectangularCamera.full(256, 128), cyl.crop(180.0))
    assert Resampler(EquirectangularCamera.full(256, 128), cyl).separable is not None
    assert Resampler(EquirectangularCamera.full(256, 128), cyl, supersample=2).separable is None


def test_a_constant_stays_constant_and_integer_input_gives_float():
    src, dst = EquirectangularCamera.full(300, 150), CylindricalCamera.full(96, 40, 1.5)
    image = torch.full((2, 3, 150, 300), 77, dtype=torch.uint8)
    out, mask = SeparableMap(src, dst)(image)
    assert out.dtype == torch.float32 and out.shape == (2, 3, 40, 96) and bool(mask.all())
    assert torch.allclose(out, torch.tensor(77.0), atol=1e-3)
    assert to_cylinder(image.double(), src, dst).dtype == torch.float64


def test_matches_dense_supersampling_in_the_limit():
    src, dst = EquirectangularCamera.full(512, 256), CylindricalCamera.full(128, 32)
    image = _smooth(256, 512)
    fast = to_cylinder(image, src, dst)
    dense = to_cylinder(image, src, dst, supersample=(8, 8))
    coarse = to_cylinder(image, src, dst, supersample=1)
    err = float((fast - dense).abs().mean())
    assert err < 0.3 * float((coarse - dense).abs().mean()) and err < 2e-3


def test_the_seam_wraps_and_the_map_turns_with_the_camera():
    src = CylindricalCamera.full(64, 16)
    image = torch.zeros(1, 1, 16, 64)
    image[..., 0] = 1.0  # one column at the seam
    out = to_cylinder(image, src, CylindricalCamera.full(32, 16))[0, 0, 8]
    # destination column 0 straddles source columns -1 and 0 and 1: half of it is the bright column
    assert abs(float(out[0]) - 0.5) < 1e-5 and abs(float(out[31]) - 0.0) < 1e-5
    turned = to_cylinder(image, src, CylindricalCamera.full(64, 16), supersample=None)
    assert torch.allclose(turned, image, atol=1e-6)  # identical cameras: the identity


def test_rows_outside_a_narrower_source_are_masked():
    src, dst = CylindricalCamera.full(128, 16, 0.5), CylindricalCamera.full(128, 32, 1.0)
    out, mask = to_cylinder(torch.ones(1, 3, 16, 128), src, dst, return_mask=True)
    rows = mask[0, 0, :, 0]
    assert not bool(rows[:6].any()) and bool(rows[10:22].all()) and not bool(rows[-6:].any())
    assert float(out[0, :, ~rows].abs().max()) == 0.0


def test_a_batch_is_its_images():
    src, dst = EquirectangularCamera.full(256, 128), CylindricalCamera.full(64, 16)
    a, b = _smooth(128, 256, 1), _smooth(128, 256, 2)
    both = to_cylinder(torch.cat([a, b]), src, dst)
    assert torch.allclose(both[1:], to_cylinder(b, src, dst), atol=1e-6)
    assert torch.allclose(both[:1], to_cylinder(a, src, dst), atol=1e-6)
