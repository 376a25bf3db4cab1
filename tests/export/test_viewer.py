"""``cylsfm export viewer``: a self-contained page (only its own files) that a headless Chromium renders
with the panorama's own resolution as texture, no black where triangles were cut or the cylinder ends, and
whose view a drag through its pointer handlers changes.

The scene: a synthetic street panorama at 1024x256 (buildings, cars and trees in front of each other, an
unknown sky) with its true depth brought down to 256x64, what a network of the demo's size gives."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cylsfm.cli import main
from cylsfm.data.io import load_depth, load_image, write_tum
from cylsfm.data.synth import generate_dataset
from cylsfm.data.synth.room import make_pose

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def _scene_data(folder: Path) -> dict:
    return json.loads((folder / "scene.js").read_text().split("=", 1)[1].rstrip().rstrip(";"))


def _image_of(url: str) -> np.ndarray:
    head, payload = url.split(",", 1)
    assert head in ("data:image/jpeg;base64", "data:image/png;base64"), head
    with Image.open(io.BytesIO(base64.b64decode(payload))) as im:
        return np.asarray(im.convert("RGB"))


@pytest.fixture(scope="module")
def page(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("viewer")
    generate_dataset(
        root / "data", sequences=1, frames=3, width=1024, height=256, seed=3, workers=1, progress=False
    )
    seq = root / "data" / "seq_000"
    np.save(root / "small.npy", load_depth(seq / "depth" / "000000.npy")[1::4, 1::4])  # 256x64
    poses = np.stack([make_pose(0.1 * i, 0.0, 0.3 * i).numpy() for i in range(5)])
    write_tum(root / "ride.txt", np.arange(5.0), poses)
    pano = seq / "images" / "000000.png"
    args = ["export", "viewer", str(pano), "--depth", str(root / "small.npy")]
    assert main([*args, str(root / "out"), "--trajectory", str(root / "ride.txt")]) == 0
    # as the viewer was: the texture and the vertices at the network's size
    assert main([*args, str(root / "small"), "--texture-width", "256", "--vertices", str(256 * 64)]) == 0
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
    data = _scene_data(out)
    assert "http" not in json.dumps(data)
    assert len(base64.b64decode(data["trajectory"])) == 5 * 12
    assert "MIT" in (out / "three-LICENSE.txt").read_text()


def test_texture_and_vertices_come_from_the_panorama_not_the_depths_size(page):
    data, small = _scene_data(page / "out"), _scene_data(page / "small")
    pano = load_image(page / "data" / "seq_000" / "images" / "000000.png")
    texture = _image_of(data["texture"])
    assert texture.shape == pano.shape  # the panorama's own 1024x256 (a JPEG of it)
    assert np.abs(texture.astype(int) - pano).mean() < 4
    assert _image_of(small["texture"]).shape == (64, 256, 3)
    n = len(base64.b64decode(data["positions"])) // 12
    uv = np.frombuffer(base64.b64decode(data["uv"]), dtype="<f4").reshape(-1, 2)
    assert len(uv) == n and 0.6 * 1025 * 256 < n <= 1025 * 256  # 1024x256 and the seam's column, less the sky
    assert uv[:, 0].min() > 0 and 1 < uv[:, 0].max() < 1 + 1 / 1024  # the split seam's column
    assert len(base64.b64decode(small["positions"])) // 12 <= 257 * 64
    faces = np.frombuffer(base64.b64decode(data["indices"]), dtype="<u4").reshape(-1, 3)
    assert faces.max() < n and len(faces) < 0.99 * 2 * n  # triangles were cut: the background must show


def test_the_budget_sets_the_density(page, tmp_path):
    pano = page / "data" / "seq_000" / "images" / "000000.png"
    args = ["export", "mesh", str(pano), str(tmp_path / "m.ply"), "--depth", str(page / "small.npy")]
    assert main([*args, "--vertices", str(512 * 128), "--points"]) == 0
    from plyfile import PlyData

    vertex = PlyData.read(tmp_path / "m.ply")["vertex"]
    known = (load_depth(page / "small.npy") > 0).mean()
    assert abs(len(vertex) / (512 * 128) - known) < 0.02


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
        "--disable-background-networking",
        "--no-first-run",
        f"--screenshot={target}",
        "--window-size=480,320",
        "--virtual-time-budget=8000",
        page.as_uri() + fragment,
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=180)
    with Image.open(target) as im:
        return np.asarray(im.convert("RGB")).astype(np.int16)


def _black(shot: np.ndarray) -> float:
    return float((shot.max(2) <= 8).mean())


def _detail(shot: np.ndarray) -> float:
    """Gradient energy: the mean squared difference of neighbouring pixels' grey values."""
    grey = shot.astype(np.float64).mean(2)
    return float((np.diff(grey, axis=0) ** 2).mean() + (np.diff(grey, axis=1) ** 2).mean())


def test_chromium_shows_the_panorama_without_holes_and_a_drag_turns_the_view(page, tmp_path):
    browser = _browser()
    if browser is None:
        pytest.skip("no Chromium to render the page (.ci/run installs Debian's chromium where it can)")
    index = page / "out" / "index.html"
    still = _screenshot(browser, index, tmp_path / "a.png")
    assert still.std() > 10, "the page rendered blank"
    pano = load_image(page / "data" / "seq_000" / "images" / "000000.png")
    assert (pano.max(2) <= 8).mean() < 0.01
    views = {
        "still": still,
        "turned": _screenshot(browser, index, tmp_path / "b.png", "#drag=200,0"),
        "down": _screenshot(browser, index, tmp_path / "c.png", "#drag=0,-300"),
        "up": _screenshot(browser, index, tmp_path / "d.png", "#drag=0,300"),
    }
    for name, shot in views.items():
        assert _black(shot) < 0.01, f"{name}: {_black(shot):.1%} of the screenshot is black"
    body = still[100:].reshape(-1, 3)[::11]  # below the caption
    colours = pano.reshape(-1, 3)[::5].astype(np.int16)
    nearest = np.abs(body[:, None, :] - colours[None, :, :]).sum(2).min(1)
    assert (nearest < 40).mean() > 0.9, "the page does not show the panorama's colours"
    for name in ("turned", "up", "down"):
        assert np.abs(views[name][100:] - still[100:]).mean() > 10, f"a drag ({name}) did not change the view"
    depth = _screenshot(browser, index, tmp_path / "e.png", "#depth")
    assert np.abs(depth[100:] - still[100:]).mean() > 10, "the depth colours did not show"
    small = _screenshot(browser, page / "small" / "index.html", tmp_path / "f.png")
    assert _black(small) < 0.01
    sharp, blurred = _detail(still[100:]), _detail(small[100:])
    assert sharp > 1.5 * blurred, (
        f"the panorama's texture is not sharper: detail {sharp:.1f} vs {blurred:.1f}"
    )


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
    pano = page / "data" / "seq_000" / "images" / "000000.png"
    args = ["export", "viewer", str(pano), str(tmp_path / "out"), "--depth", str(page / "small.npy")]
    assert main([*args, "--vertices", "4096", "--trajectory", str(tmp_path / "ride.txt")]) == 0
    positions = np.frombuffer(base64.b64decode(_scene_data(tmp_path / "out")["trajectory"]), dtype="<f4")
    expected = [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [0.5, 0.25, 1.0]]
    np.testing.assert_allclose(positions.reshape(-1, 3), expected, atol=1e-6)


# The page's script run by Node.js on the real three.js, with a stand-in for the browser: no WebGL renderer
# (it keeps the camera it was asked to draw with), no textures, pointer events dispatched by hand.
NODE_PAGE = r"""
const fs = require("fs"), path = require("path");
const dir = process.argv[2];
const THREE = require(path.join(dir, "three.min.js"));
global.THREE = THREE;
function eventTarget() {
  const handlers = {};
  return {
    addEventListener(type, fn) { (handlers[type] = handlers[type] || []).push(fn); },
    dispatchEvent(e) { (handlers[e.type] || []).forEach((fn) => fn(e)); },
  };
}
const canvas = eventTarget();
global.window = Object.assign(eventTarget(), {
  innerWidth: 480, innerHeight: 320, devicePixelRatio: 1, location: { hash: process.argv[3] },
});
global.PointerEvent = function (type, init) { return Object.assign({ type: type }, init); };
global.atob = (s) => Buffer.from(s, "base64").toString("binary");
global.document = {
  title: "", body: { appendChild() {} },
  getElementById() { return { addEventListener() {}, textContent: "" }; },
};
let drawnWith = null;
THREE.WebGLRenderer = function () {
  return {
    domElement: canvas, capabilities: { getMaxAnisotropy: () => 1 },
    setPixelRatio() {}, setSize() {}, render(scene, camera) { drawnWith = camera; },
  };
};
THREE.TextureLoader = function () { return { load() { return new THREE.Texture(); } }; };
eval(fs.readFileSync(path.join(dir, "scene.js"), "utf8"));
eval(fs.readFileSync(path.join(dir, "viewer.js"), "utf8"));
drawnWith.updateMatrixWorld();
const ahead = new THREE.Vector3(0, 0, -10).project(drawnWith);  // straight ahead before any drag
process.stdout.write(JSON.stringify([ahead.x * window.innerWidth / 2, -ahead.y * window.innerHeight / 2]));
"""


@pytest.mark.parametrize("drag", [(100, 0), (-100, 0), (0, 60), (0, -60), (80, -50)])
def test_a_drag_moves_the_scene_with_the_pointer(page, tmp_path, drag):
    """The page's pointer handlers, run by Node.js: after a drag of (dx, dy) pixels (#drag=DX,DY, as a
    user's), what was straight ahead is on the screen about (dx, dy) pixels from the centre: the scene
    follows the pointer (dragging right turns the view left, dragging down tilts it up), not the reverse."""
    node = shutil.which("node") or shutil.which("nodejs")
    if node is None:
        pytest.skip("no Node.js to run the page's script")
    script = tmp_path / "page.js"
    script.write_text(NODE_PAGE)
    hash_ = f"#drag={drag[0]},{drag[1]}"
    out = subprocess.run(
        [node, str(script), str(page / "out"), hash_], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    moved = np.array(json.loads(out.stdout))
    for axis, (want, got) in enumerate(zip(drag, moved, strict=True)):
        if want == 0:
            assert abs(got) < 1, f"{hash_}: the scene moved {got:.1f} px along axis {axis}"
        else:
            assert 0.6 < got / want < 1.4, (
                f"{hash_}: what was ahead moved by {moved.round(1)} px on the screen"
            )
