import json
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cylsfm.geometry import Camera, CameraError, CylindricalCamera, PinholeCamera, load_camera

sizes = st.sampled_from([(64, 16), (128, 32), (512, 128), (96, 40)])


@settings(max_examples=40, deadline=None)
@given(size=sizes, seed=st.integers(0, 2**31 - 1), vfov=st.floats(0.3, 2.0), batch=st.integers(1, 3))
def test_cylindrical_unproject_then_project_is_identity(size, seed, vfov, batch):
    w, h = size
    cam = CylindricalCamera.full(w, h, vfov_h=vfov)
    gen = torch.Generator().manual_seed(seed)
    depth = torch.rand(batch, 1, h, w, generator=gen, dtype=torch.float64) * 79 + 0.05
    points = cam.unproject(depth)
    uv = cam.project(points)
    grid = cam.pixel_grid(batch, dtype=torch.float64)
    du = torch.remainder(uv[:, 0] - grid[:, 0] + w / 2, w) - w / 2  # azimuth is periodic
    assert du.abs().max() < 1e-9
    assert (uv[:, 1] - grid[:, 1]).abs().max() < 1e-9
    assert torch.allclose(cam.depth_of(points), depth, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), fov=st.floats(20, 150))
def test_pinhole_unproject_then_project_is_identity(seed, fov):
    cam = PinholeCamera.from_fov(96, 40, fov)
    gen = torch.Generator().manual_seed(seed)
    depth = torch.rand(2, 1, 40, 96, generator=gen, dtype=torch.float64) * 50 + 0.1
    points = cam.unproject(depth)
    assert torch.allclose(cam.project(points), cam.pixel_grid(2, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(cam.depth_of(points), depth)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(-50, 50), y=st.floats(-20, 20), z=st.floats(-50, 50), scale=st.floats(0.1, 10))
def test_cylindrical_project_then_unproject_recovers_points(x, y, z, scale):
    if x * x + z * z < 1e-4:
        return
    cam = CylindricalCamera.full(512, 128)
    p = torch.tensor([x, y, z], dtype=torch.float64).view(1, 3, 1, 1)
    uv = cam.project(p)
    ray = cam.rays(uv)
    assert torch.allclose(ray * cam.depth_of(p), p, atol=1e-9)
    # projection is scale invariant: every point of the ray lands on the same pixel
    assert torch.allclose(cam.project(p * scale), uv, atol=1e-9)


def test_cylindrical_formulas_by_hand():
    cam = CylindricalCamera(width=360, height=100, fx=360 / (2 * math.pi), cx=180.0, fy=50.0, cy=49.5)
    # 2 m right, 1 m down, 2 m forward: theta = 45 degrees, d = 2 sqrt 2, h = 1 / (2 sqrt 2)
    p = torch.tensor([2.0, 1.0, 2.0], dtype=torch.float64).view(1, 3, 1, 1)
    u, v = cam.project(p).flatten().tolist()
    assert u == pytest.approx(180 + 45)
    assert v == pytest.approx(49.5 + 50 / (2 * math.sqrt(2)))
    assert cam.depth_of(p).item() == pytest.approx(2 * math.sqrt(2))
    # straight behind the camera is the seam (u = 0 == u = W)
    back = torch.tensor([1e-9, 0.0, -3.0], dtype=torch.float64).view(1, 3, 1, 1)
    u_back = cam.project(back)[0, 0].item()
    assert min(u_back % 360, 360 - u_back % 360) == pytest.approx(0, abs=1e-6)


def test_project_is_differentiable_on_the_axis():
    cam = CylindricalCamera.full(64, 16)
    p = torch.zeros(1, 3, 1, 1, requires_grad=True)
    cam.project(p).sum().backward()
    assert torch.isfinite(p.grad).all()
    assert not cam.projectable(p.detach()).any()


def test_wraps_and_scales():
    cam = CylindricalCamera.full(512, 128)
    assert cam.wraps
    for s in (0.5, 0.25, 0.125):
        small = cam.scaled(s)
        assert small.wraps
        assert small.size == (round(512 * s), round(128 * s))
    half = cam.scaled(0.5)
    # pixel centres of a 2x downsampled image lie between the old ones
    assert half.cx == pytest.approx(128 - 0.25)
    assert half.fx == pytest.approx(256 / (2 * math.pi))
    # a resize maps image edges to image edges
    assert (cam.cx + 0.5) / cam.width == pytest.approx((half.cx + 0.5) / half.width)
    assert not PinholeCamera.from_fov(64, 32, 90).wraps
    crop = cam.crop(180)
    assert not crop.wraps and crop.width == 256
    assert crop.hfov_deg == pytest.approx(180)


def test_crop_keeps_the_forward_direction_and_the_rays():
    cam = CylindricalCamera.full(512, 128)
    for fov in (100, 180, 270, 360):
        x0, x1 = cam.crop_window(fov)
        crop = cam.crop(fov)
        assert crop.width == x1 - x0 == round(512 * fov / 360)
        # the rays of the crop's pixels are those of the same columns of the full panorama
        uv_full = cam.pixel_grid(1, dtype=torch.float64)[..., x0:x1]
        uv_crop = crop.pixel_grid(1, dtype=torch.float64)
        assert torch.allclose(cam.rays(uv_full), crop.rays(uv_crop))
        theta_mid = (crop.width / 2 - 0.5 - crop.cx) / crop.fx
        assert abs(theta_mid) <= 0.5 / crop.fx + 1e-12
    assert cam.crop(360).wraps
    with pytest.raises(CameraError):
        cam.crop(400)


def test_json_round_trip_and_errors(tmp_path):
    cam = CylindricalCamera.full(512, 128)
    path = tmp_path / "camera.json"
    cam.to_json(path)
    assert load_camera(path) == cam
    assert CylindricalCamera.from_json(path) == cam
    pin = PinholeCamera.from_fov(640, 480, 90)
    pin.to_json(tmp_path / "pin.json")
    assert isinstance(Camera.from_json(tmp_path / "pin.json"), PinholeCamera)
    with pytest.raises(CameraError, match="expected 'cylindrical'"):
        CylindricalCamera.from_json(tmp_path / "pin.json")

    bad = tmp_path / "bad.json"
    cases = {
        "{not json": "not valid JSON",
        json.dumps(
            {"model": "fisheye", "width": 1, "height": 1, "fx": 1, "cx": 0, "fy": 1, "cy": 0}
        ): "unknown",
        json.dumps({"model": "cylindrical", "width": 512, "height": 128, "fx": 1, "cx": 0, "fy": 1}): "cy",
        json.dumps(
            {"model": "cylindrical", "width": 512, "height": 128, "fx": -1, "cx": 0, "fy": 1, "cy": 0}
        ): "fx",
        json.dumps(
            {"model": "cylindrical", "width": 51.5, "height": 128, "fx": 1, "cx": 0, "fy": 1, "cy": 0}
        ): "width",
        json.dumps(
            {"model": "cylindrical", "width": 512, "height": 128, "fx": "a", "cx": 0, "fy": 1, "cy": 0}
        ): "fx",
        json.dumps([1, 2]): "JSON object",
    }
    for text, needle in cases.items():
        bad.write_text(text)
        with pytest.raises(CameraError, match=needle) as info:
            load_camera(bad)
        assert str(bad) in str(info.value)
    with pytest.raises(CameraError, match="not found"):
        load_camera(tmp_path / "missing.json")


def test_batched_intrinsics_match_per_camera_results():
    cams = [CylindricalCamera.full(64, 16, v) for v in (0.5, 1.0, 1.5)]
    stacked = Camera.stack(cams)
    depth = torch.rand(3, 1, 16, 64) + 1
    pts = stacked.unproject(depth)
    for i, cam in enumerate(cams):
        assert torch.allclose(pts[i : i + 1], cam.unproject(depth[i : i + 1]))
        assert stacked.index(i) == cam
    diff = stacked.project(pts) - stacked.pixel_grid(3)
    diff[:, 0] = torch.remainder(diff[:, 0] + 32, 64) - 32  # azimuth is periodic
    assert diff.abs().max() < 1e-3
    assert stacked.wraps


def test_equirectangular_conventions_and_round_trip():
    from cylsfm.geometry import EquirectangularCamera

    cam = EquirectangularCamera.full(360, 180)
    assert cam.wraps
    # straight ahead is the image centre: x_e = W/2 - 1/2, y_e = H/2 - 1/2
    p = torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64).view(1, 3, 1, 1)
    assert cam.project(p).flatten().tolist() == pytest.approx([179.5, 89.5])
    # 45 degrees right and 30 degrees down
    d = torch.tensor(
        [math.cos(math.pi / 6) * math.sin(math.pi / 4), 0.5, math.cos(math.pi / 6) * math.cos(math.pi / 4)]
    )
    u, v = cam.project((3 * d).double().view(1, 3, 1, 1)).flatten().tolist()
    assert u == pytest.approx(360 * (1 / 8 + 0.5) - 0.5) and v == pytest.approx(180 * (1 / 6 + 0.5) - 0.5)
    depth = torch.rand(2, 1, 180, 360, dtype=torch.float64) * 30 + 0.5
    pts = cam.unproject(depth)
    assert torch.allclose(cam.depth_of(pts), depth)
    diff = cam.project(pts) - cam.pixel_grid(2, dtype=torch.float64)
    diff[:, 0] = torch.remainder(diff[:, 0] + 180, 360) - 180
    assert diff.abs().max() < 1e-8
