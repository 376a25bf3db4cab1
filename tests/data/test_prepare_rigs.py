"""``cylsfm prepare views`` / ``synthia`` / ``headcam``: pinhole views stitched into the direct cylindrical
render (colour and depth), SYNTHIA's layout with its poses' convention found, static frames left out, and
the Headcam videos prepared as the paper did, with its excluded-frames numbering."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import av
import numpy as np
import pytest
import torch

from cylsfm.cli import main
from cylsfm.data.format import load_depth, load_image, scan_dataset
from cylsfm.data.io import save_png, write_tum
from cylsfm.data.prepare import RigOptions, SynthiaOptions, prepare_synthia, prepare_views
from cylsfm.data.stitch import view_rotation
from cylsfm.data.synth.render import render_frame
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera, EquirectangularCamera, PinholeCamera, inverse_warp, invert
from synthia_standin import VIEW_AXES, write_synthia_standin

VIEWS = (("front", 0.0), ("right", 90.0), ("back", 180.0), ("left", 270.0))
OUT_W, OUT_H = 128, 32


def _u8(image: torch.Tensor) -> np.ndarray:
    return (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * math.log10(255.0**2 / max(mse, 1e-12))


def _edges(depth: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood (wrapping around the seam) spans a depth ratio above 1.05."""
    t = torch.from_numpy(depth)[None, None]
    t = torch.cat([t[..., -1:], t, t[..., :1]], -1)
    hi = torch.nn.functional.max_pool2d(t, 3, 1, padding=(1, 0))[0, 0]
    lo = -torch.nn.functional.max_pool2d(-t, 3, 1, padding=(1, 0))[0, 0]
    return (hi > 1.05 * lo).numpy()


def _rig_poses() -> list[torch.Tensor]:
    return [make_pose(0.4 - 0.15 * i, 0.1, -1.2 + 0.3 * i, yaw_deg=20.0 + 6.0 * i) for i in range(3)]


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """Four 100-degree pinhole views (and z-depth) of the room per frame, a rig file, the direct renders."""
    root = tmp_path_factory.mktemp("rig") / "room"
    camera = PinholeCamera.from_fov(120, 72, 100.0)
    views = []
    for name, yaw in VIEWS:
        (root / name).mkdir(parents=True)
        (root / f"{name}_depth").mkdir()
        camera.to_json(root / f"{name}.json")
        views.append(
            {"name": name, "images": name, "depth": f"{name}_depth", "camera": f"{name}.json", "yaw": yaw}
        )
    poses = _rig_poses()
    for i, c2w in enumerate(poses):
        for name, yaw in VIEWS:
            turn = torch.eye(4, dtype=torch.float64)
            turn[:3, :3] = torch.from_numpy(VIEW_AXES[yaw])  # the axes written out, not the stitcher's
            image, z = render_room(camera, c2w @ turn, supersample=3)
            save_png(root / name / f"{i:04d}.png", _u8(image))
            np.save(root / f"{name}_depth" / f"{i:04d}.npy", z[0, 0].numpy())
    write_tum(root / "poses.txt", np.arange(3) / 5.0, torch.stack(poses).numpy())
    (root / "rig.json").write_text(json.dumps({"views": views, "poses": "poses.txt"}))
    cyl = CylindricalCamera.full(OUT_W, OUT_H, 0.5)
    direct = [render_room(cyl, c2w, supersample=4) for c2w in poses]
    return {"rig": root / "rig.json", "camera": cyl, "direct": direct, "poses": poses}


def test_views_give_the_direct_cylindrical_render_and_depth(rig, tmp_path):
    options = RigOptions(size=(OUT_W, OUT_H), vfov_h=0.5)
    path, n, _ = prepare_views(rig["rig"], tmp_path / "data", options, progress=False)
    seq = scan_dataset(tmp_path / "data")[0]
    assert n == 3 and seq.path == path and seq.camera.to_dict() == rig["camera"].to_dict()
    assert seq.mask is None  # four 100-degree views see all of |h| <= 0.5
    for img, dpath, (image, depth) in zip(seq.images, seq.depths, rig["direct"], strict=True):
        assert _psnr(load_image(img), _u8(image)) >= 30.0
        truth, got = depth[0, 0].numpy(), load_depth(dpath)
        rel = np.abs(got - truth) / truth
        # within 1% except along occlusion edges (where a view's pixel grid cannot say which side a ray is)
        assert float(np.median(rel)) < 1e-3 and float((rel < 0.01).mean()) >= 0.97
        assert float((rel < 0.01)[~_edges(truth)].mean()) >= 0.995
    assert np.allclose(seq.poses, torch.stack(rig["poses"]).numpy(), atol=1e-6)
    # the prepared frames, depth and poses make inverse_warp reproduce the target
    images = [
        torch.from_numpy(np.array(load_image(p))).permute(2, 0, 1)[None].float() / 255 for p in seq.images
    ]
    depth0 = torch.from_numpy(load_depth(seq.depths[0]))[None, None]
    rel_pose = torch.from_numpy(invert(torch.from_numpy(seq.poses[1])).numpy() @ seq.poses[0])
    warped, valid = inverse_warp(images[1], depth0, rel_pose[None].float(), seq.camera)
    err = ((warped - images[0]).abs() * valid).sum() / valid.sum() / 3
    assert valid.float().mean() > 0.8 and float(err) < 0.04


def test_view_rotation_from_first_principles():
    """The stitcher's view axes against the axes written out in the tests (yaw right, pitch up, roll clockwise)."""
    for yaw, axes in VIEW_AXES.items():
        assert np.allclose(view_rotation(yaw), axes, atol=1e-12), yaw
    s, c = math.sin(math.radians(30)), math.cos(math.radians(30))
    assert np.allclose(view_rotation(0.0, 90.0) @ [0, 0, 1], [0, -1, 0])  # pitched up: looks along -y (up)
    assert np.allclose(view_rotation(90.0, 30.0) @ [0, 0, 1], [c, -s, 0])  # turned right, then up
    assert np.allclose(
        view_rotation(0.0, 0.0, 90.0) @ [1, 0, 0], [0, 1, 0]
    )  # clockwise: its right points down


@pytest.mark.parametrize(("lit", "azimuth"), [("right", 90.0), ("left", -90.0), ("back", 180.0)])
def test_a_view_lands_at_its_azimuth(tmp_path, lit, azimuth):
    """Only one view of the rig is white: the panorama is white around the column of its azimuth
    (u = W/(2 pi) theta + W/2, theta = atan2(x, z)), as ``prepare views`` reads the rig file's yaws."""
    root = tmp_path / "rig"
    face = PinholeCamera.from_fov(32, 32, 90.0)
    views = []
    for name, yaw in VIEWS:
        (root / name).mkdir(parents=True)
        save_png(root / name / "0000.png", np.full((32, 32, 3), 255 if name == lit else 0, np.uint8))
        views.append({"name": name, "images": name, "camera": face.to_dict(), "yaw": yaw})
    (root / "rig.json").write_text(json.dumps({"views": views, "fps": 5}))
    width = 64
    path, n, _ = prepare_views(
        root / "rig.json", tmp_path / "out", RigOptions(size=(width, 16), vfov_h=0.5), progress=False
    )
    row = np.asarray(load_image(next((path / "images").iterdir())))[8, :, 0].astype(np.float64) / 255
    u = np.arange(width)
    centre = width / (2 * math.pi) * math.radians(azimuth) + width / 2  # 48 right, 16 left, 0 (= 64) behind
    offset = (u - centre + width / 2) % width - width / 2  # columns from the centre, across the seam
    assert n == 1 and abs(float((row * offset).sum() / row.sum())) < 1.0
    assert row[np.abs(offset) <= 6].min() > 0.9 and row[np.abs(offset) >= 10].max() < 0.1  # a 90-degree view


def test_views_resume_mask_and_bad_rigs(rig, tmp_path):
    out = tmp_path / "data"
    options = RigOptions(size=(OUT_W, OUT_H), vfov_h=1.0)
    path, _, _ = prepare_views(rig["rig"], out, options, progress=False)
    # |h| up to 1: the corners between the views are unseen, black, and left out by the mask
    mask = np.asarray(load_image(path / "mask.png"))[..., 0] > 127
    assert mask[OUT_H // 2].all() and not mask.all()
    stamps = {p.name: p.stat().st_mtime_ns for p in (path / "images").iterdir()}
    prepare_views(rig["rig"], out, options, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in (path / "images").iterdir()} == stamps
    spec = json.loads(rig["rig"].read_text())
    bad = rig["rig"].parent / "bad.json"
    missing = dict(spec, views=[*spec["views"][:3], dict(spec["views"][3], images="front_depth")])
    bad.write_text(json.dumps(missing))
    with pytest.raises(CylsfmError, match="missing in view left"):
        prepare_views(bad, tmp_path / "o", progress=False)
    bad.write_text(json.dumps(dict(spec, views=[dict(spec["views"][0], images="../../etc")])))
    with pytest.raises(CylsfmError, match="outside the rig's folder"):
        prepare_views(bad, tmp_path / "o", progress=False)
    bad.write_text("{not json")
    with pytest.raises(CylsfmError, match=r"bad\.json"):
        prepare_views(bad, tmp_path / "o", progress=False)


@pytest.mark.parametrize("convention", ["y-up", "x-flip-inv"])
def test_synthia_layout_convention_static_frames_and_depth(tmp_path, convention, capsys):
    scene, truth = write_synthia_standin(tmp_path / "in", convention=convention, sides=("left", "right"))
    code = main(
        [
            "prepare",
            "synthia",
            str(tmp_path / "in"),
            str(tmp_path / "out"),
            "--size",
            "128x32",
            "--no-progress",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert f"poses as {convention} (chosen" in printed and "1 left out as static" in printed
    seqs = {s.path.name: s for s in scan_dataset(tmp_path / "out")}
    assert sorted(seqs) == ["02-SPRING-left", "02-SPRING-right"]
    cyl = CylindricalCamera.full(128, 32, 0.5)
    for side in ("left", "right"):
        seq = seqs[f"02-SPRING-{side}"]
        kept = [int(p.stem) for p in seq.images]
        assert kept == [0, 1, 2, 4, 5]  # frame 3 repeats frame 2: a camera standing still
        assert np.allclose(seq.poses, np.stack([truth[side][k] for k in kept]), atol=1e-5)
    seq = seqs["02-SPRING-left"]
    for k, img, dpath in zip(kept, seq.images, seq.depths, strict=True):
        image, depth = render_frame(replace(scene, c2w=truth["left"][k][None]), 0, cyl, supersample=4)
        assert _psnr(load_image(img), image) >= 30.0
        got = load_depth(dpath)
        both = (depth > 0) & (got > 0)
        assert float((both == (depth > 0)).mean()) > 0.98  # sky (65535) stays unknown
        rel = np.abs(got - depth) / np.maximum(depth, 1e-6)
        inner = both & ~_edges(depth)  # the street's many small objects: edges are much of the picture
        assert float(np.median(rel[both])) < 2e-3 and float((rel[inner] < 0.01).mean()) > 0.97
    assert (tmp_path / "out" / "splits" / "default" / "train.txt").is_file()


def test_synthia_bad_inputs(tmp_path):
    write_synthia_standin(tmp_path / "in", frames=(0, 1, 2))
    folder = tmp_path / "in" / "SYNTHIA-SEQS-02-SPRING"
    with pytest.raises(CylsfmError, match="unknown pose convention"):
        prepare_synthia(tmp_path / "in", tmp_path / "o", SynthiaOptions(convention="z-up"), progress=False)
    with pytest.raises(CylsfmError, match="no SYNTHIA-SEQS"):
        prepare_synthia(tmp_path / "in", tmp_path / "o", SynthiaOptions(sequences=("04",)), progress=False)
    (folder / "Depth" / "Stereo_Left" / "Omni_B" / "000001.png").unlink()
    with pytest.raises(CylsfmError, match=r"Omni_B/000001\.png: missing"):
        prepare_synthia(tmp_path / "in", tmp_path / "o", SynthiaOptions(sides=("left",)), progress=False)
    (folder / "CameraParams" / "intrinsics.txt").write_text("focal\n")
    with pytest.raises(CylsfmError, match=r"intrinsics\.txt"):
        prepare_synthia(tmp_path / "in", tmp_path / "o", SynthiaOptions(sides=("left",)), progress=False)


def _day_video(path, n: int) -> None:
    """An equirectangular 128x64 lossless video at 30 fps: frame i shows i bright columns."""
    cam = EquirectangularCamera.full(128, 64)
    base = _u8(render_room(cam, make_pose(0.0, 0.1, 0.0), supersample=1)[0])
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=30)
        stream.width, stream.height, stream.pix_fmt = 128, 64, "bgr0"
        for i in range(n):
            frame = base.copy()
            frame[:, :i] = 255
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)


def test_headcam_five_fps_excluded_frames_and_split(tmp_path, capsys):
    root = tmp_path / "headcam"
    root.mkdir()
    _day_video(root / "2018-10-02.mkv", 13)
    _day_video(root / "2018-10-03.mkv", 7)
    (tmp_path / "excluded.txt").write_text("2018-10-02 1\n2018-10-03/0  # a car in front\n")
    args = ["prepare", "headcam", str(root), str(tmp_path / "out"), "--size", "64x16", "--no-progress"]
    assert main([*args, "--exclude", str(tmp_path / "excluded.txt")]) == 0
    names = {s.path.name: [p.stem for p in s.images] for s in scan_dataset(tmp_path / "out")}
    # 5 of 30 fps: every 6th frame from the first (ffmpeg's fps=5); the list counts them from 0
    assert names == {"2018-10-02": ["000000", "000012"], "2018-10-03": ["000006"]}
    assert "by frame" in capsys.readouterr().out
    # numbered as ffmpeg's %05d files (from 1): '1' is the first frame
    out1 = tmp_path / "out1"
    other = [*args[:3], str(out1), *args[4:]]
    assert main([*other, "--exclude", str(tmp_path / "excluded.txt"), "--exclude-numbering", "1"]) == 2
    assert "start at 1" in capsys.readouterr().err  # 2018-10-03/0 cannot be a frame of a 1-based list
    (tmp_path / "ffmpeg.txt").write_text("2018-10-02 1\n")
    assert (
        main(
            [*other, "--exclude", str(tmp_path / "ffmpeg.txt"), "--exclude-numbering", "1", "--split", "none"]
        )
        == 0
    )
    assert [p.stem for p in scan_dataset(out1)[0].images] == ["000006", "000012"]
    (tmp_path / "bare.txt").write_text("3\n")
    assert main([*other, "--exclude", str(tmp_path / "bare.txt"), "--overwrite"]) == 2
    assert "name the video" in capsys.readouterr().err
    assert main(["prepare", "headcam", str(tmp_path / "excluded.txt"), str(out1)]) == 2
    assert "folder not found" in capsys.readouterr().err


def test_abutting_cube_faces_leave_no_seam():
    from cylsfm.data.stitch import Stitcher, View

    face = PinholeCamera.from_fov(64, 64, 90.0)  # four faces meeting exactly at their outer edges
    views = [View(str(yaw), face, view_rotation(yaw)) for yaw in (0.0, 90.0, 180.0, 270.0)]
    for width in (256, 512):  # seams on pixel centres (width % 8 == 0) and between them
        stitcher = Stitcher(views, CylindricalCamera.full(width, 32, 0.5))
        colour = stitcher.colour([np.full((64, 64, 3), 100, np.uint8)] * 4)
        assert stitcher.coverage.all() and (colour == 100).all()


def test_rig_values_are_checked(rig, tmp_path):
    spec = json.loads(rig["rig"].read_text())
    bad = rig["rig"].parent / "bad_values.json"
    for change, message in (
        ({"views": [dict(spec["views"][0], yaw="left")]}, "'yaw' must be a number"),
        ({"fps": 0}, "'fps' must be a positive number"),
        ({"depth_scale": "cm"}, "'depth_scale' must be a number"),
    ):
        bad.write_text(json.dumps({**spec, **change}))
        with pytest.raises(CylsfmError, match=message):
            prepare_views(bad, tmp_path / "o", progress=False)
