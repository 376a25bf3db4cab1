"""``cylsfm export viewer``: a self-contained page (only its own files) that a headless Chromium renders
with the panorama's colours, and whose view a drag through its pointer handlers changes."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cylsfm.cli import main
from cylsfm.data.io import load_image, save_png, write_tum
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.geometry import CylindricalCamera

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


@pytest.fixture(scope="module")
def page(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("viewer")
    cam = CylindricalCamera.full(256, 64)
    image, depth = render_room(cam, make_pose(0.3, 0.1, -0.5, yaw_deg=10.0), supersample=2)
    save_png(root / "pano.png", (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy())
    np.save(root / "depth.npy", depth[0, 0].numpy())
    poses = np.stack([make_pose(0.1 * i, 0.0, 0.3 * i).numpy() for i in range(5)])
    write_tum(root / "ride.txt", np.arange(5.0), poses)
    args = ["export", "viewer", str(root / "pano.png"), str(root / "out"), "--depth", str(root / "depth.npy")]
    assert main([*args, "--trajectory", str(root / "ride.txt")]) == 0
    return root


def test_the_page_needs_nothing_from_outside(page):
    out = page / "out"
    assert sorted(p.name for p in out.iterdir()) == [
        "index.html",
        "scene.js",
        "three-LICENSE.txt",
        "three.min.js",
        "viewer.js",
    ]
    html = (out / "index.html").read_text()
    assert re.findall(r'src="([^"]+)"', html) == ["three.min.js", "scene.js", "viewer.js"]
    assert "http" not in html and "http" not in (out / "viewer.js").read_text()
    data = json.loads((out / "scene.js").read_text().split("=", 1)[1].rstrip().rstrip(";"))
    import base64

    n = len(base64.b64decode(data["positions"])) // 12
    assert n == 256 * 64 and len(base64.b64decode(data["colours"])) == 3 * n
    assert len(base64.b64decode(data["trajectory"])) == 5 * 12
    assert "MIT" in (out / "three-LICENSE.txt").read_text()


def test_the_trajectory_is_the_poses_seen_from_the_first(page, tmp_path):
    """The trajectory written into the page: little-endian float32 positions of the TUM poses in the frame
    of the first camera (x right, y down, z forward), worked out by hand for a camera that starts at
    (1, 0, 2) looking along the world's +x, moves 1 m ahead, 0.5 m to its right, then 0.25 m down."""
    poses = [
        make_pose(1.0, 0.0, 2.0, yaw_deg=90.0),
        make_pose(2.0, 0.0, 2.0, yaw_deg=90.0),
        make_pose(2.0, 0.0, 1.5, yaw_deg=120.0),  # its own turn does not move it
        make_pose(2.0, 0.25, 1.5, yaw_deg=120.0),
    ]
    write_tum(tmp_path / "ride.txt", np.arange(4.0), np.stack([p.numpy() for p in poses]))
    args = [
        "export",
        "viewer",
        str(page / "pano.png"),
        str(tmp_path / "out"),
        "--depth",
        str(page / "depth.npy"),
    ]
    assert main([*args, "--trajectory", str(tmp_path / "ride.txt")]) == 0
    data = json.loads((tmp_path / "out" / "scene.js").read_text().split("=", 1)[1].rstrip().rstrip(";"))
    import base64

    positions = np.frombuffer(base64.b64decode(data["trajectory"]), dtype="<f4").reshape(-1, 3)
    expected = [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [0.5, 0.25, 1.0]]
    np.testing.assert_allclose(positions, expected, atol=1e-6)


def _browser() -> str | None:
    return next((b for b in map(shutil.which, BROWSERS) if b), None)


def _screenshot(browser: str, page: Path, target: Path, fragment: str = "") -> np.ndarray:
    cmd = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--enable-unsafe-swiftshader",
        "--use-angle=swiftshader",
        f"--screenshot={target}",
        "--window-size=480,320",
        "--virtual-time-budget=4000",
        page.as_uri() + fragment,
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    with Image.open(target) as im:
        return np.asarray(im.convert("RGB")).astype(np.int16)


def test_chromium_shows_the_panorama_and_a_drag_turns_the_view(page, tmp_path):
    browser = _browser()
    if browser is None:
        pytest.skip("no Chromium to render the page (.ci/run installs Debian's chromium where it can)")
    index = page / "out" / "index.html"
    still = _screenshot(browser, index, tmp_path / "a.png")
    dragged = _screenshot(browser, index, tmp_path / "b.png", "#drag=160,0")
    depth = _screenshot(browser, index, tmp_path / "c.png", "#depth")
    body = still[100:]  # below the caption
    assert body.std() > 10, "the page rendered blank"
    pano = load_image(page / "pano.png").reshape(-1, 3)[::7].astype(np.int16)
    shown = body.reshape(-1, 3)[::11]
    shown = shown[shown.sum(1) > 30]  # not the black gaps where discontinuities were cut
    nearest = np.abs(shown[:, None, :] - pano[None, :, :]).sum(2).min(1)
    assert len(shown) > 0.8 * body.reshape(-1, 3)[::11].shape[0] and (nearest < 40).mean() > 0.9
    assert np.abs(dragged[100:] - body).mean() > 10, "a drag did not change the view"
    assert np.abs(depth[100:] - body).mean() > 10, "the depth colours did not show"
