"""``cylsfm export mesh`` / ``stereo``: meshes whose vertices reproject to their pixels with the seam closed
and discontinuities cut, metric scale from the camera height, ODS pairs with the analytic disparity and
no foreground smeared into disocclusions, and the command line on ground truth and on a checkpoint."""

from __future__ import annotations

import math

import av
import numpy as np
import pytest
import torch
from plyfile import PlyData

from cylsfm.cli import main
from cylsfm.data.io import save_png
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.export.mesh import build_mesh
from cylsfm.export.ods import anaglyph, ods_pair, render_eye, stereo_layout
from cylsfm.export.scene import Scene, load_scene
from cylsfm.export.stereo import StereoOptions, _clip_factor
from cylsfm.geometry import CylindricalCamera, EquirectangularCamera
from cylsfm.geometry.ground import ground_height
from helpers import untrained_checkpoint

W, H = 128, 32


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A cylindrical render of the room (a box stands in it: depth discontinuities) with its true depth."""
    root = tmp_path_factory.mktemp("room")
    cam = CylindricalCamera.full(W, H)
    image, depth = render_room(cam, make_pose(0.3, 0.1, -0.5, yaw_deg=10.0), supersample=2)
    rgb = (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()
    save_png(root / "pano.png", rgb)
    np.save(root / "depth.npy", depth[0, 0].numpy())
    return {"root": root, "scene": Scene(rgb, depth[0, 0].numpy(), cam, "metres", "metres (truth)")}


def _edges(faces: np.ndarray) -> dict[tuple[int, int], int]:
    count: dict[tuple[int, int], int] = {}
    for a, b in np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]):
        key = (min(a, b), max(a, b))
        count[key] = count.get(key, 0) + 1
    return count


def test_mesh_reprojects_closes_the_seam_and_cuts_discontinuities(room):
    scene = room["scene"]
    mesh = build_mesh(scene)
    uv = scene.camera.project(torch.from_numpy(mesh.vertices).T.reshape(1, 3, -1, 1).double())[0, :, :, 0].T
    uv = uv.numpy()
    du = (uv[:, 0] - mesh.pixels[:, 0] + W / 2) % W - W / 2  # column 0 is azimuth -180 = +180 degrees
    assert np.abs(du).max() < 1e-3 and np.abs(uv[:, 1] - mesh.pixels[:, 1]).max() < 1e-3
    assert np.allclose(mesh.colours, scene.image[mesh.pixels[:, 1], mesh.pixels[:, 0]])
    col = mesh.pixels[:, 0]
    seam = [(a, b) for a, b in _edges(mesh.faces) if {col[a], col[b]} == {0, W - 1}]
    assert seam, "no triangle crosses the seam"
    # closed: without culling the only open edges are the top and bottom rows' (a cylinder's two rims)
    whole = build_mesh(scene, max_ratio=1e6)
    boundary = [(a, b) for (a, b), n in _edges(whole.faces).items() if n == 1]
    rows = whole.pixels[:, 1]
    assert len(boundary) == 2 * W and all(rows[a] == rows[b] and rows[a] in (0, H - 1) for a, b in boundary)
    # and the seam is like any other column: turning the panorama changes nothing
    turned = Scene(
        np.roll(scene.image, W // 2, 1), np.roll(scene.depth, W // 2, 1), scene.camera, "metres", ""
    )
    assert len(build_mesh(turned).faces) == len(mesh.faces)
    depth = np.linalg.norm(mesh.vertices[:, [0, 2]], axis=1)
    corner = depth[mesh.faces]
    assert (corner.max(1) <= 1.2 * corner.min(1) + 1e-6).all()
    uncut = build_mesh(scene, max_ratio=1e6)
    assert len(uncut.faces) > len(mesh.faces)  # the box's silhouette: triangles bridging it were cut
    longest = lambda m: np.linalg.norm(m.vertices[m.faces[:, 0]] - m.vertices[m.faces[:, 1]], axis=1).max()  # noqa: E731
    assert longest(uncut) > 3 * longest(mesh)
    # unknown depth (the sky of ground truth) gives no vertex
    holed = Scene(
        scene.image,
        np.where(np.arange(W) < 10, 0.0, scene.depth).astype(np.float32),
        scene.camera,
        "metres",
        "",
    )
    assert len(build_mesh(holed).vertices) == (W - 10) * H


def test_metric_scale_from_the_camera_height(room):
    scene = room["scene"]
    height = float(ground_height(torch.from_numpy(scene.depth)[None, None], scene.camera)[0])
    assert math.isfinite(height)
    relative = scene.scaled(0.37, "network units", "relative")
    metric = relative.to_metres(height)
    assert metric.unit == "metres" and np.allclose(metric.depth, scene.depth, rtol=1e-3)
    assert "metres" in metric.scale_note


def test_cli_mesh_and_points_from_depth_and_checkpoint(room, tmp_path, capsys):
    root = room["root"]
    args = [
        "export",
        "mesh",
        str(root / "pano.png"),
        str(tmp_path / "m.ply"),
        "--depth",
        str(root / "depth.npy"),
    ]
    assert main(args) == 0
    ply = PlyData.read(str(tmp_path / "m.ply"))
    assert ply["vertex"].count == W * H and ply["face"].count > 0
    assert any("scale: metres" in c for c in ply.comments)
    assert main([*args[:3], str(tmp_path / "p.ply"), *args[4:], "--points"]) == 0
    assert [e.name for e in PlyData.read(str(tmp_path / "p.ply")).elements] == ["vertex"]
    ckpt = untrained_checkpoint(tmp_path)
    assert (
        main(["export", "mesh", str(root / "pano.png"), str(tmp_path / "n.ply"), "--checkpoint", str(ckpt)])
        == 0
    )
    assert any("relative" in c for c in PlyData.read(str(tmp_path / "n.ply")).comments)
    capsys.readouterr()
    with pytest.raises(SystemExit):  # a depth source is required
        main(["export", "mesh", str(root / "pano.png"), str(tmp_path / "x.ply")])
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((3, 3, 3), np.float32))
    assert main([*args[:4], "--depth", str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err


def _blob_scene(depth: float, width: int = 512, height: int = 128) -> Scene:
    x = np.arange(width)
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[..., 0] = np.round(255 * np.exp(-0.5 * ((x - 100.3) / 3) ** 2))
    cam = CylindricalCamera.full(width, height)
    return Scene(rgb, np.full((height, width), depth, np.float32), cam, "metres", "")


def _centre(image: np.ndarray) -> float:
    row = image[image.shape[0] // 2, :, 0].astype(float)
    return float((row * np.arange(len(row))).sum() / row.sum())


@pytest.mark.parametrize("depth", [0.6, 2.0, 8.0])
def test_ods_disparity_is_the_analytic_one(depth):
    scene = _blob_scene(depth)
    left, _ = render_eye(scene, scene.camera, 0.064, "left")
    right, _ = render_eye(scene, scene.camera, 0.064, "right")
    expected = 2 * math.asin(0.032 / depth) * scene.camera.width / (2 * math.pi)
    assert abs((_centre(left) - _centre(right)) - expected) < 0.5
    assert abs((_centre(left) + _centre(right)) / 2 - 100.3) < 0.25  # symmetric about the source


def test_disocclusions_take_the_background():
    w, h = 512, 64
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 2] = 255  # blue background at 10 m
    depth = np.full((h, w), 10.0, np.float32)
    rgb[:, 200:240] = (255, 0, 0)  # a red foreground 40 columns wide at 0.5 m
    depth[:, 200:240] = 0.5
    scene = Scene(rgb, depth, CylindricalCamera.full(w, h), "metres", "")
    for eye in ("left", "right"):
        image, d = render_eye(scene, scene.camera, 0.064, eye)
        red = (image[h // 2, :, 0] > 128).sum()
        assert abs(int(red) - 40) <= 1 and (d > 0).all()  # shifted, not widened: the holes are blue
        assert ((image[h // 2, :, 0] > 128) | (image[h // 2, :, 2] > 128)).all()


def test_layouts_anaglyph_and_equirect():
    scene = _blob_scene(2.0, 128, 32)
    left, _ = render_eye(scene, scene.camera, 0.064, "left")
    right, _ = render_eye(scene, scene.camera, 0.064, "right")
    assert stereo_layout(left, right, "top-bottom").shape == (64, 128, 3)
    assert stereo_layout(left, right, "side-by-side").shape == (32, 256, 3)
    red_cyan = anaglyph(left, right)
    assert (red_cyan[..., 0] == left[..., 0]).all() and (red_cyan[..., 1:] == right[..., 1:]).all()
    eq, d = render_eye(scene, EquirectangularCamera.full(128, 64), 0.064, "left")
    rows = (d > 0).any(1)
    assert eq.shape == (64, 128, 3) and rows[32] and not rows[0] and not rows[-1]  # +-45 degrees only


def test_cli_stereo_image_and_video(room, tmp_path, capsys):
    root = room["root"]
    out = tmp_path / "st.png"
    args = ["export", "stereo", str(root / "pano.png"), str(out), "--depth", str(root / "depth.npy")]
    assert main([*args, "--anaglyph", "--equirect", "--width", "256"]) == 0
    assert out.is_file() and (tmp_path / "st_anaglyph.png").is_file()
    from cylsfm.data.io import load_image

    assert load_image(out).shape == (256, 256, 3)  # two 256x128 equirectangular eyes, top-bottom
    video = tmp_path / "in.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("mpeg4", rate=5)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        for k in range(3):
            frame = np.roll(room["scene"].image, 4 * k, axis=1)
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    ckpt = untrained_checkpoint(tmp_path)
    assert (
        main(
            [
                "export",
                "stereo",
                str(video),
                str(tmp_path / "st.mp4"),
                "--checkpoint",
                str(ckpt),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "one scale for the clip" in capsys.readouterr().out
    with av.open(str(tmp_path / "st.mp4")) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 3 and frames[0].shape == (2 * H, W, 3)
    assert (
        main(["export", "stereo", str(video), str(tmp_path / "x.mp4"), "--depth", str(root / "depth.npy")])
        == 2
    )


def test_one_scale_for_the_clip(room):
    scene = room["scene"]
    frames = [scene.scaled(f, "network units", "") for f in (1.0, 2.0, 4.0)]
    factor, note = _clip_factor(frames, StereoOptions(median_depth=3.0))
    both = np.concatenate([f.depth.ravel() for f in frames])
    assert abs(float(np.median(both)) * factor - 3.0) < 1e-3 and "one scale" in note


def test_load_scene_finds_a_dataset_frames_camera(tmp_path, room):
    seq = tmp_path / "seq"
    (seq / "images").mkdir(parents=True)
    cam = CylindricalCamera.full(W, H, 0.5)
    cam.to_json(seq / "camera.json")
    save_png(seq / "images" / "000000.png", room["scene"].image)
    np.save(tmp_path / "d.npy", room["scene"].depth)
    scene = load_scene(seq / "images" / "000000.png", depth=tmp_path / "d.npy")
    assert scene.camera.to_dict() == cam.to_dict()


# ---------------------------------------------------------------------------------------------------
# The left eye is the left eye: a near object, seen from the eye beside the centre on the viewer's left
# (x right, z forward: looking along +z the left eye is at -x), appears turned to the right, i.e. at a
# larger azimuth and column than from the centre, and the right eye's at a smaller one.
def _white_stripe(depth: float, width: int, height: int, column: float) -> Scene:
    x = np.arange(width)
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[...] = np.round(255 * np.exp(-0.5 * ((x - column) / 3) ** 2))[None, :, None]
    return Scene(
        rgb, np.full((height, width), depth, np.float32), CylindricalCamera.full(width, height), "metres", ""
    )


def _seen_column(eye: str, azimuth: float, rho: float, ipd: float, width: int) -> float:
    """The column at which an eye of a viewer turning on the spot sees a point at ``azimuth`` and horizontal
    distance ``rho``: the gaze ``a`` (finely searched) for which the point lies straight ahead of the eye
    ``ipd / 2`` beside the centre, to the left (``left``) or right of the gaze ``(sin a, 0, cos a)``."""
    a = azimuth + np.linspace(-0.5, 0.5, 200001)
    side = -1.0 if eye == "left" else 1.0  # the gaze's right hand is (cos a, 0, -sin a)
    ex, ez = side * ipd / 2 * np.cos(a), -side * ipd / 2 * np.sin(a)
    px, pz = rho * math.sin(azimuth) - ex, rho * math.cos(azimuth) - ez  # eye to point
    across = px * np.cos(a) - pz * np.sin(a)  # sideways from the gaze: 0 when the point is ahead
    best = a[np.argmin(np.where(px * np.sin(a) + pz * np.cos(a) > 0, np.abs(across), np.inf))]
    return float(best) * width / (2 * math.pi) + width / 2  # u = fx theta + cx


def test_the_left_eye_sees_a_near_object_turned_right_in_every_layout():
    width, rho, ipd = 256, 0.5, 0.2
    column = 100.3
    scene = _white_stripe(rho, width, 32, column)
    azimuth = (column - width / 2) * 2 * math.pi / width
    left_at, right_at = (_seen_column(e, azimuth, rho, ipd, width) for e in ("left", "right"))
    assert left_at - column == pytest.approx(column - right_at, abs=0.01) and left_at > column + 7
    left, right = ods_pair(scene, scene.camera, ipd)
    assert _centre(left) == pytest.approx(left_at, abs=0.3) and _centre(right) == pytest.approx(
        right_at, abs=0.3
    )
    top_bottom = stereo_layout(left, right, "top-bottom")
    assert _centre(top_bottom[:32]) == pytest.approx(left_at, abs=0.3)  # the left eye on top
    assert _centre(top_bottom[32:]) == pytest.approx(right_at, abs=0.3)
    side = stereo_layout(left, right, "side-by-side")
    assert _centre(side[:, :width]) == pytest.approx(left_at, abs=0.3)  # the left eye on the left
    assert _centre(side[:, width:]) == pytest.approx(right_at, abs=0.3)
    red_cyan = anaglyph(left, right)  # red for the left eye (a red filter over it), cyan for the right
    assert _centre(red_cyan[..., [0, 0, 0]]) == pytest.approx(left_at, abs=0.3)
    assert _centre(red_cyan[..., [1, 1, 1]]) == pytest.approx(right_at, abs=0.3)


@pytest.mark.parametrize("layout", ["top-bottom", "side-by-side"])
def test_cli_stereo_puts_the_left_eye_first(tmp_path, layout):
    width, height, rho, ipd, column = 256, 32, 0.5, 0.2, 100.3
    scene = _white_stripe(rho, width, height, column)
    save_png(tmp_path / "pano.png", scene.image)
    np.save(tmp_path / "depth.npy", scene.depth)
    out = tmp_path / "st.png"
    args = ["export", "stereo", str(tmp_path / "pano.png"), str(out), "--depth", str(tmp_path / "depth.npy")]
    assert main([*args, "--ipd", str(ipd), "--layout", layout, "--anaglyph"]) == 0
    from cylsfm.data.io import load_image

    pair = np.asarray(load_image(out))
    first, second = (
        (pair[:height], pair[height:]) if layout == "top-bottom" else (pair[:, :width], pair[:, width:])
    )
    azimuth = (column - width / 2) * 2 * math.pi / width
    assert _centre(first) == pytest.approx(_seen_column("left", azimuth, rho, ipd, width), abs=0.5)
    assert _centre(second) == pytest.approx(_seen_column("right", azimuth, rho, ipd, width), abs=0.5)
    red_cyan = np.asarray(load_image(tmp_path / "st_anaglyph.png"))
    assert _centre(red_cyan[..., [0, 0, 0]]) - _centre(red_cyan[..., [1, 1, 1]]) > 10  # red: the left eye


def test_cli_stereo_video_puts_the_left_eye_on_top(tmp_path):
    """A video through a network's depth (relative, one scale for the clip) and a wide IPD: in every frame
    the near stripe sits further right in the top (left) eye than in the bottom one."""
    stripe = _white_stripe(1.0, W, H, 40.3).image
    video = tmp_path / "in.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("mpeg4", rate=5)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        for _ in range(2):
            for packet in stream.encode(av.VideoFrame.from_ndarray(stripe, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    out = tmp_path / "st.mp4"
    args = ["export", "stereo", str(video), str(out), "--checkpoint", str(untrained_checkpoint(tmp_path))]
    assert main([*args, "--ipd", "1.0", "--no-progress"]) == 0
    with av.open(str(out)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 2
    for frame in frames:
        assert _centre(frame[:H]) - _centre(frame[H:]) > 4.0  # 2 asin(0.5 / 3) is 6.8 columns


def test_sigterm_stops_a_stereo_video_and_the_same_command_continues(tmp_path, monkeypatch, capsys):
    """SIGTERM during the stereo pass of a video: exit status 143, the work so far kept in OUT.parts/ (every
    frame's depth, the first pairs), no video; the same command continues without predicting or rendering
    again what was done, removes the parts, and its video's frames equal an uninterrupted export's."""
    import os
    import signal

    from cylsfm.export import stereo

    rng = np.random.default_rng(4)
    video = tmp_path / "in.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("mpeg4", rate=5)
        stream.width, stream.height, stream.pix_fmt = 128, 32, "yuv420p"
        for _ in range(6):
            frame = rng.integers(0, 256, (32, 128, 3), dtype=np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    ckpt = untrained_checkpoint(tmp_path)
    args = ["export", "stereo", str(video), "--checkpoint", str(ckpt), "--device", "cpu", "--no-progress"]
    assert main([*args, str(tmp_path / "whole.mp4")]) == 0
    render, calls = stereo._render, {"n": 0}

    def signalled(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return render(*a, **k)

    monkeypatch.setattr(stereo, "_render", signalled)
    capsys.readouterr()
    out = tmp_path / "cut.mp4"
    assert main([*args, str(out)]) == 143
    assert "interrupted by SIGTERM" in capsys.readouterr().err
    parts = tmp_path / "cut.mp4.parts"
    assert not out.exists() and len(list((parts / "depth").iterdir())) == 6
    pairs = sorted((parts / "frames").iterdir())
    assert 2 <= len(pairs) < 6
    import cylsfm.export.scene as scene_module

    scene_function, predicted, rendered = scene_module.scene_function, {"n": 0}, {"n": 0}

    def counting_scenes(*a, **k):
        inner = scene_function(*a, **k)

        def scene_of(rgb, depth=None):
            predicted["n"] += depth is None
            return inner(rgb, depth=depth)

        return scene_of

    def counting_render(*a, **k):
        rendered["n"] += 1
        return render(*a, **k)

    monkeypatch.setattr(scene_module, "scene_function", counting_scenes)
    monkeypatch.setattr(stereo, "_render", counting_render)
    assert main([*args, str(out)]) == 0
    assert predicted["n"] == 0 and rendered["n"] == 6 - len(pairs)  # nothing predicted or rendered twice
    assert not parts.exists()

    def frames(path):
        with av.open(str(path)) as container:
            return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]

    a, b = frames(tmp_path / "whole.mp4"), frames(out)
    assert len(a) == len(b) == 6 and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_a_videos_frames_in_one_network_call_equal_one_by_one(tmp_path) -> None:
    """The stereo export predicts a video's frames in batches (SceneFunction.many): the same scenes as one
    frame at a time, to float tolerance."""
    from cylsfm.export.scene import scene_function

    g = torch.Generator().manual_seed(3)
    coarse = torch.rand(5, 3, 8, 32, generator=g)
    frames = torch.nn.functional.interpolate(coarse, size=(64, 256), mode="bicubic", align_corners=False)
    rgbs = list((frames.clamp(0, 1) * 255).round().byte().permute(0, 2, 3, 1).numpy())
    scene_of = scene_function(
        tmp_path / "ride.mp4", untrained_checkpoint(tmp_path), None, "cpu", None, amp=False
    )
    together = scene_of.many(rgbs)
    assert len(together) == 5
    for rgb, scene in zip(rgbs, together, strict=True):
        alone = scene_of(rgb)
        np.testing.assert_allclose(scene.depth, alone.depth, rtol=1e-5)
        assert np.array_equal(scene.image, alone.image) and scene.unit == alone.unit
