"""The street generator: ground truth that explains the images, determinism, projections, dataset output."""

import json

import numpy as np
import pytest
import torch

from cylsfm import inverse_warp
from cylsfm.data.synthetic import StreetScene, SynthConfig, generate_dataset, make_camera, render_frame
from cylsfm.geometry import relative_pose, transform_points


@pytest.fixture(scope="module")
def scene():
    return StreetScene.generate(123, SynthConfig(frames=12, moving_cars=0))


def _warp_ratios(scene, camera, tgt, src):
    """(ratio on pixels the source sees, ratio on all valid pixels) of unwarped / warped photometric error."""
    img_t, depth_t = render_frame(scene, tgt, camera)
    img_s, depth_s = render_frame(scene, src, camera)
    to_t = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float() / 255  # noqa: E731
    t_img, s_img = to_t(img_t), to_t(img_s)
    depth = torch.from_numpy(depth_t)[None, None]
    T = relative_pose(torch.from_numpy(scene.c2w[tgt]), torch.from_numpy(scene.c2w[src])).float()[None]
    warped, valid = inverse_warp(s_img, depth, T, camera)
    valid = valid & (depth > 0)  # the sky has no depth to warp with
    # occlusion is not an error of the ground truth: keep the pixels whose 3D point the source sees
    expected = camera.depth_of(transform_points(T, camera.unproject(depth)))
    seen, _ = inverse_warp(torch.from_numpy(depth_s)[None, None], depth, T, camera)
    visible = valid & ((seen - expected).abs() < 0.05 * expected)
    out = []
    for mask in (visible, valid):
        m = mask.float()
        err_warp = float(((warped - t_img).abs() * m).sum() / m.sum())
        err_none = float(((s_img - t_img).abs() * m).sum() / m.sum())
        out.append(err_none / err_warp)
    return out


@pytest.mark.parametrize(
    ("projection", "size"), [("cylindrical", (512, 128)), ("pinhole", (256, 64)), ("equirect", (512, 256))]
)
def test_ground_truth_explains_the_next_frame(scene, projection, size):
    """Warping frame t+1 into frame t with the true depth and relative pose beats no warping 5x."""
    camera = make_camera(projection, *size)
    for t in (2, 7):
        visible, valid = _warp_ratios(scene, camera, t, t + 1)
        assert visible > 5, (t, visible)
        assert valid > 3.5, (t, valid)  # occlusions included


def test_camera_moves_like_a_cyclist(scene):
    steps = np.linalg.norm(np.diff(scene.c2w[:, :3, 3], axis=0), axis=1)
    assert 0.0 <= steps.min() and steps.max() < 2.0 and 0.5 < np.median(steps) < 1.5
    heights = -scene.c2w[:, 1, 3]
    assert np.all((heights > 1.5) & (heights < 2.0))
    # gravity (world +y) stays within a few degrees of the camera's down axis
    down = scene.c2w[:, :3, 1]
    tilt = np.degrees(np.arccos(np.clip(down[:, 1], -1, 1)))
    assert tilt.max() < 8


def test_rendering_is_deterministic_and_seeded():
    cfg = SynthConfig(frames=5, moving_cars=3)
    cam = make_camera("cylindrical", 128, 32)
    a = StreetScene.generate(7, cfg)
    b = StreetScene.generate(7, cfg)
    c = StreetScene.generate(8, cfg)
    ia, da = render_frame(a, 3, cam)
    ib, db = render_frame(b, 3, cam)
    ic, _ = render_frame(c, 3, cam)
    assert np.array_equal(ia, ib) and np.array_equal(da, db)
    assert np.array_equal(a.c2w, b.c2w)
    assert not np.array_equal(ia, ic)


def test_images_have_detail_everywhere(scene):
    """Photometric matching needs gradients: ground and facades are textured, not flat colours."""
    img, depth = render_frame(scene, 4, make_camera("cylindrical", 256, 64))
    grey = img.astype(np.float64).mean(2)
    grad = np.abs(np.diff(grey, axis=1))
    ground = (depth > 0) & (np.arange(64)[:, None] > 40)
    assert grad[ground[:, 1:]].mean() > 1.0  # grey levels per pixel on the ground
    assert (depth == 0).mean() > 0.03 and (depth == 0)[-1].sum() == 0  # sky on top, none at the bottom


def test_moving_cars_move_and_keep_clear_of_the_camera():
    sc = StreetScene.generate(5, SynthConfig(frames=30, moving_cars=8))
    assert len(sc.movers) == 8
    p0, p1 = sc.prisms_at(0), sc.prisms_at(10)
    n = len(sc.static)
    assert len(p0) == n + 3 * 8
    assert not np.allclose(p0.a[n:], p1.a[n:])


def test_generate_dataset_writes_format_v1(tmp_path):
    dirs = generate_dataset(
        tmp_path, sequences=2, frames=4, width=128, height=32, seed=3, workers=1, progress=False
    )
    assert [d.name for d in dirs] == ["seq_000", "seq_001"]
    for d in dirs:
        cam = json.loads((d / "camera.json").read_text())
        assert cam["model"] == "cylindrical" and cam["width"] == 128
        assert len(list((d / "images").glob("*.png"))) == 4
        assert len(list((d / "depth").glob("*.npy"))) == 4
        lines = [
            line for line in (d / "poses.txt").read_text().splitlines() if line and not line.startswith("#")
        ]
        assert len(lines) == 4
    a = (dirs[0] / "images" / "000002.png").read_bytes()
    again = generate_dataset(
        tmp_path / "again", sequences=1, frames=4, width=128, height=32, seed=3, workers=2, progress=False
    )
    assert (again[0] / "images" / "000002.png").read_bytes() == a  # the same with parallel workers
