"""``cylsfm predict``: images, folders, videos and equirectangular footage with an (untrained) checkpoint."""

import json
from pathlib import Path

import av
import numpy as np
import pytest
import torch
from PIL import Image

from cylsfm.cli import main
from cylsfm.data.convert import to_cylinder
from cylsfm.export.colorize import colorize_depth, depth_limits
from cylsfm.geometry import Camera, CylindricalCamera, EquirectangularCamera, PinholeCamera
from cylsfm.model import Predictor
from cylsfm.predict import MIN_COVERAGE, coverage, model_camera, predict
from helpers import untrained_checkpoint


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    """An untrained checkpoint at 128x32 (aspect 4), full panoramas."""
    return untrained_checkpoint(tmp_path_factory.mktemp("ckpt"))


@pytest.fixture(scope="module")
def crop_ckpt(tmp_path_factory) -> Path:
    """An untrained checkpoint of 90-degree crops of 512x32 panoramas (the network sees 128x32)."""
    return untrained_checkpoint(tmp_path_factory.mktemp("crop"), 512, 32, fov=90.0)


def _expected_depth(predictor: Predictor, rgb: np.ndarray, camera: Camera, convert_to=None) -> np.ndarray:
    """The depth ``predict`` must write for one ``uint8 [H,W,3]`` frame: the predictor's own output on
    the frame (first resampled by the library's conversion when ``convert_to`` is given)."""
    x = torch.from_numpy(np.array(rgb)).permute(2, 0, 1)[None].float() / 255
    if convert_to is not None:
        x = to_cylinder(x, camera, convert_to).clamp(0, 1)
        camera = convert_to
    return predictor.depth(x, camera)[0, 0].numpy()


def _load_rgb(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def _png(path: Path, width: int, height: int, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rng.integers(0, 256, (height, width, 3), dtype=np.uint8)).save(path)
    return path


def _video(path: Path, frames: int = 6, size=(256, 64), rate: int = 10) -> Path:
    rng = np.random.default_rng(1)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=rate)
        stream.width, stream.height, stream.pix_fmt = size[0], size[1], "yuv420p"
        for _ in range(frames):
            arr = rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(arr, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    return path


def _run(ckpt, *args) -> int:
    return main(["predict", "--checkpoint", str(ckpt), "--device", "cpu", *map(str, args)])


def _no_temporaries(out: Path) -> None:
    assert not [p for p in out.rglob(".*")], list(out.rglob(".*"))


def test_images_and_a_folder(ckpt, tmp_path, capsys):
    a = _png(tmp_path / "in" / "a.png", 512, 128, 0)
    b = _png(tmp_path / "in" / "b.jpg", 512, 128, 1)
    folder = tmp_path / "frames"
    for i in range(3):
        _png(folder / f"f{i:02d}.png", 256, 64, i)
    (folder / "notes.txt").write_text("not an image")
    out = tmp_path / "out"
    assert _run(ckpt, a, b, folder, "--out", out, "--batch-size", "2") == 0
    assert "wrote 5 depth maps of 3 input(s)" in capsys.readouterr().out
    predictor = Predictor.from_checkpoint(ckpt, "cpu")
    inputs = [("a", a), ("b", b)] + [("frames", folder / f"f{i:02d}.png") for i in range(3)]
    for name, image in inputs:
        depth = np.load(out / name / f"{image.stem}.npy")
        rgb = _load_rgb(image)
        h, w = rgb.shape[:2]
        assert depth.dtype == np.float32 and depth.shape == (h, w)
        assert np.isfinite(depth).all() and (depth > 0).all()
        # the predictor's own depth of this very frame, taken as a full cylinder of the model's field of view
        want = _expected_depth(predictor, rgb, CylindricalCamera.full(w, h, 1.0))
        np.testing.assert_allclose(depth, want, rtol=1e-4)
        with Image.open(out / name / f"{image.stem}.png") as im:
            # a readable picture: the frame above its depth, each enlarged k times to >= 1024 wide
            k = -(-1024 // w)
            assert im.mode == "RGB" and im.size[0] == k * w >= 1024 and im.size[1] > 2 * k * h
            panel = np.asarray(im)[k * h + 2 : 2 * k * h + 2]
            # one colour range for every picture of an input, from its frames (a lone image: its own)
            scale = json.loads((out / name / "scale.json").read_text())
            assert scale["unit"] == "network units" and scale["factor"] == 1.0
            if name != "frames":
                assert np.allclose(scale["colour_range"], depth_limits(depth))
            coloured = colorize_depth(depth, *scale["colour_range"])
            np.testing.assert_array_equal(panel, np.repeat(np.repeat(coloured, k, 0), k, 1))
    assert sorted(p.name for p in (out / "frames").iterdir()) == sorted(
        [f"f{i:02d}.{s}" for i in range(3) for s in ("npy", "png")] + ["scale.json"]
    )
    _no_temporaries(out)


def test_video_with_preview_and_fps(ckpt, tmp_path):
    vid = _video(tmp_path / "ride.mp4")
    out = tmp_path / "out"
    assert _run(ckpt, vid, "--out", out, "--no-png", "--batch-size", "4") == 0
    names = sorted(p.name for p in (out / "ride").iterdir())
    assert names == [f"{i:06d}.npy" for i in range(6)] + ["scale.json"]  # --no-png
    predictor = Predictor.from_checkpoint(ckpt, "cpu")
    with av.open(str(vid)) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    for i in (0, 5):
        depth = np.load(out / "ride" / f"{i:06d}.npy")
        assert depth.shape == (64, 256)
        want = _expected_depth(predictor, decoded[i], CylindricalCamera.full(256, 64, 1.0))
        np.testing.assert_allclose(depth, want, rtol=1e-4)
    with av.open(str(out / "ride.mp4")) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        assert stream.codec_context.name in ("h264", "mpeg4")
    assert len(frames) == 6
    h, w = frames[0].shape[:2]
    assert w == 256 and h == 64 + 2 + 64 and h % 2 == 0 and w % 2 == 0  # input above depth
    _no_temporaries(out)
    # --fps 5 on a 10 fps video keeps every other frame, named by their index in the video
    out2 = tmp_path / "out2"
    assert _run(ckpt, vid, "--out", out2, "--fps", "5") == 0
    assert sorted(p.stem for p in (out2 / "ride").glob("*.npy")) == ["000000", "000002", "000004"]
    with av.open(str(out2 / "ride.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 3


def test_equirectangular_input_is_converted_to_the_model_cylinder(ckpt, tmp_path, capsys):
    img = _png(tmp_path / "pano.png", 256, 128)
    cam = tmp_path / "camera.json"
    EquirectangularCamera.full(256, 128).to_json(cam)
    # without --camera a 2:1 image is taken as equirectangular (the model takes 4:1 cylinders), and said so
    assert _run(ckpt, img, "--out", tmp_path / "auto") == 0
    assert "taken as equirectangular" in capsys.readouterr().err
    odd = _png(tmp_path / "odd.png", 300, 100)  # 3:1 is neither: refused
    assert _run(ckpt, odd, "--out", tmp_path / "refused") == 2
    out = tmp_path / "out"
    assert _run(ckpt, img, "--out", out, "--camera", cam) == 0
    depth = np.load(out / "pano" / "pano.npy")
    assert depth.shape == (32, 128)  # the converted cylinder, at the network's input size
    # the model's cylinder: full 360 degrees, the training vertical field of view
    predictor = Predictor.from_checkpoint(ckpt, "cpu")
    target = model_camera(predictor)
    assert target.size == (128, 32) and target.wraps
    assert target.height / (2 * target.fy) == pytest.approx(1.0)
    # the depth is the predictor's on the library's conversion into that cylinder
    rgb = _load_rgb(img)
    want = _expected_depth(predictor, rgb, EquirectangularCamera.full(256, 128), convert_to=target)
    np.testing.assert_allclose(depth, want, rtol=1e-4)
    # and not the depth of the same pixels merely resized (the equirectangular rows span +-90 degrees)
    resized = _expected_depth(predictor, rgb, CylindricalCamera.full(256, 128, 1.0))
    resized = torch.nn.functional.interpolate(
        torch.from_numpy(resized)[None, None], size=(32, 128), mode="area"
    )
    assert not np.allclose(depth, resized[0, 0].numpy(), rtol=1e-3)
    # a cylindrical camera.json of the training field of view is used as it is (depth at input size)
    cyl = tmp_path / "cyl.json"
    CylindricalCamera.full(512, 128).to_json(cyl)
    wide = _png(tmp_path / "wide.png", 512, 128)
    summary = predict(predictor, [wide], tmp_path / "out3", camera=cyl, progress=False)
    assert summary.total == 1 and np.load(tmp_path / "out3" / "wide" / "wide.npy").shape == (128, 512)


def test_wrong_aspect_is_refused_naming_the_file(ckpt, tmp_path, capsys):
    bad = _png(tmp_path / "square.png", 100, 100)
    out = tmp_path / "out"
    assert _run(ckpt, bad, "--out", out) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "square.png" in err and "100x100" in err
    assert "4.000" in err and "--camera" in err
    assert not (out / "square").exists()
    # a pinhole camera is refused too: it covers a quarter of the full panorama the model sees
    cam = tmp_path / "pinhole.json"
    PinholeCamera.from_fov(100, 100, 90).to_json(cam)
    assert _run(ckpt, bad, "--out", out, "--camera", cam) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pinhole" in err and "full 360-degree panoramas" in err
    assert not (out / "square").exists()


def test_pinhole_input_feeds_a_model_trained_on_crops_it_covers(crop_ckpt, tmp_path, capsys):
    """A 120-degree pinhole view covers the 90-degree crop the network sees: it is converted into the
    model's cylinder and its depth is the predictor's on that conversion; a 60-degree view is refused."""
    predictor = Predictor.from_checkpoint(crop_ckpt, "cpu")
    target = model_camera(predictor)
    assert target.size == (512, 32) and predictor.window(target) == (192, 320)
    wide = PinholeCamera.from_fov(160, 160, 120)
    assert coverage(wide, target, predictor.window(target)) == 1.0
    assert coverage(wide, target, None) < 0.5  # a third of the turn at most
    img = _png(tmp_path / "photo.png", 160, 160)
    cam = tmp_path / "pinhole.json"
    wide.to_json(cam)
    out = tmp_path / "out"
    assert _run(crop_ckpt, img, "--out", out, "--camera", cam) == 0
    depth = np.load(out / "photo" / "photo.npy")
    assert depth.shape == (32, 128)  # the crop the network sees, at its input size
    want = _expected_depth(predictor, _load_rgb(img), wide, convert_to=target)
    np.testing.assert_allclose(depth, want, rtol=1e-4)
    narrow = tmp_path / "narrow.json"
    PinholeCamera.from_fov(160, 160, 60).to_json(narrow)
    assert _run(crop_ckpt, img, "--out", tmp_path / "out2", "--camera", narrow) == 2
    err = capsys.readouterr().err
    assert coverage(PinholeCamera.from_fov(160, 160, 60), target, (192, 320)) < MIN_COVERAGE
    assert "narrow.json" in err and "90-degree crops" in err and "covers" in err
    assert not (tmp_path / "out2" / "photo").exists()


def test_corrupt_inputs_are_one_line_errors(ckpt, tmp_path, capsys):
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    assert _run(ckpt, junk, "--out", tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "junk.png" in err and "Traceback" not in err
    vid = tmp_path / "clip.mp4"
    vid.write_bytes(b"\x00\x00\x00\x18ftypmp42 garbage garbage garbage")
    assert _run(ckpt, vid, "--out", tmp_path / "out") == 2
    assert "clip.mp4" in capsys.readouterr().err
    assert _run(ckpt, tmp_path / "missing.png", "--out", tmp_path / "out") == 2
    assert "missing.png" in capsys.readouterr().err


def test_a_failure_midway_keeps_what_was_written(ckpt, tmp_path, capsys):
    good = _png(tmp_path / "in" / "good.png", 512, 128)
    whole = _png(tmp_path / "cut.png", 512, 128).read_bytes()
    cut = tmp_path / "in" / "cut.png"
    cut.write_bytes(whole[: len(whole) // 2])  # the header is fine, the pixels are not
    out = tmp_path / "out"
    assert _run(ckpt, good, cut, "--out", out) == 2
    assert "cut.png" in capsys.readouterr().err
    assert np.load(out / "good" / "good.npy").shape == (128, 512)
    assert (out / "good" / "good.png").exists()
    _no_temporaries(out)


def test_same_names_do_not_collide(ckpt, tmp_path):
    a = _png(tmp_path / "x" / "pano.png", 512, 128, 0)
    b = _png(tmp_path / "y" / "pano.png", 512, 128, 1)
    summary = predict(ckpt, [a, b], tmp_path / "out", device="cpu", progress=False)
    assert sorted(summary.frames) == ["pano", "pano-2"]
    assert (tmp_path / "out" / "pano-2" / "pano.npy").exists()
    assert json.loads(json.dumps(summary.total)) == 2


def test_full_resolution_depth_in_the_inputs_own_camera(ckpt, tmp_path):
    img = _png(tmp_path / "pano.png", 256, 128)  # equirectangular (2:1)
    out = tmp_path / "out"
    assert _run(ckpt, img, "--out", out, "--full-resolution") == 0
    net = np.load(out / "pano" / "pano.npy")
    full = np.load(out / "pano" / "pano_full.npy")
    assert net.shape == (32, 128) and full.shape == (128, 256)
    # the model sees +-45 degrees: the poles are unknown (0), the band known
    assert (full[:20] == 0).all() and (full[-20:] == 0).all() and (full[40:88] > 0).all()
    # at the horizon, equirectangular range equals the cylinder's depth, one network pixel per 2 columns
    row = full[63:65].mean(0)
    centre = net[15:17].mean(0)
    assert np.allclose(row[::2], centre, rtol=0.15)
    with Image.open(out / "pano" / "pano_full.png") as im:
        assert im.size[0] == 256


def test_sigterm_stops_predict_and_the_same_command_continues(ckpt, tmp_path, monkeypatch, capsys):
    """SIGTERM (a scheduler preempting the job) during the third batch of a video: exit status 143 with one
    line, the frames written so far kept whole, no preview left half-written; the same command then keeps
    them, predicts the rest, and its files equal an uninterrupted run's byte for byte (the preview's frames
    too)."""
    import os
    import signal

    from cylsfm.predict import run as predict_run

    vid = _video(tmp_path / "ride.mp4", frames=10)
    args = [vid, "--batch-size", "2"]
    assert _run(ckpt, *args, "--out", tmp_path / "whole") == 0
    batch, calls = predict_run._run_batch, {"n": 0}

    def signalled(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return batch(*a, **k)

    monkeypatch.setattr(predict_run, "_run_batch", signalled)
    capsys.readouterr()
    cut = tmp_path / "cut"
    assert _run(ckpt, *args, "--out", cut) == 143
    assert "interrupted by SIGTERM" in capsys.readouterr().err
    kept = sorted(p.name for p in (cut / "ride").iterdir())
    assert 4 <= len(kept) < 20 and not (cut / "ride.mp4").exists()
    _no_temporaries(cut)
    stamps = {p.name: p.stat().st_mtime_ns for p in (cut / "ride").iterdir()}
    monkeypatch.setattr(predict_run, "_run_batch", batch)
    assert _run(ckpt, *args, "--out", cut) == 0
    assert "kept from an interrupted run" in capsys.readouterr().out
    for name, stamp in stamps.items():
        assert (cut / "ride" / name).stat().st_mtime_ns == stamp  # not computed again
    whole = sorted(p.name for p in (tmp_path / "whole" / "ride").iterdir())
    assert sorted(p.name for p in (cut / "ride").iterdir()) == whole
    for name in whole:
        assert (cut / "ride" / name).read_bytes() == (tmp_path / "whole" / "ride" / name).read_bytes(), name

    def frames(path):
        with av.open(str(path)) as container:
            return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]

    a, b = frames(tmp_path / "whole" / "ride.mp4"), frames(cut / "ride.mp4")
    assert len(a) == len(b) == 10 and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    # other settings: nothing is kept (a different batch size could change the values in the last bit)
    assert _run(ckpt, vid, "--batch-size", "3", "--out", cut) == 0
    assert "kept" not in capsys.readouterr().out


def _ground_plane_depth(self, images, camera, mask=None):
    """A stand-in network: every frame sees a level ground ``1 + mean colour`` units below the camera
    (and a wall 5 units away above the horizon), so each frame has its own scale."""
    h = camera.rays(camera.pixel_grid(1, dtype=torch.float64))[0, 1].float()  # y / d per pixel
    below = h > 0.05
    depth = []
    for image in images:
        height = 1.0 + float(image.mean())
        depth.append(torch.where(below, height / h.clamp(min=1e-3), torch.full_like(h, 5.0)))
    return torch.stack(depth)[:, None]


def test_camera_height_gives_metres_by_one_factor_for_the_whole_input(ckpt, tmp_path, monkeypatch, capsys):
    from cylsfm.geometry.ground import ground_height

    monkeypatch.setattr(Predictor, "depth", _ground_plane_depth)
    folder = tmp_path / "ride"
    for i in range(5):
        _png(folder / f"f{i}.png", 128, 32, i)
    out = tmp_path / "out"
    assert _run(ckpt, folder, "--out", out, "--camera-height", "1.6") == 0
    assert "metres: one factor for every frame" in capsys.readouterr().err
    scale = json.loads((out / "ride" / "scale.json").read_text())
    assert scale["unit"] == "metres" and scale["ground_fits"] == scale["frames_sampled"] == 5
    cam = CylindricalCamera.full(128, 32, 1.0)
    heights = [1.0 + _load_rgb(folder / f"f{i}.png").mean() / 255 for i in range(5)]
    assert scale["factor"] == pytest.approx(1.6 / np.median(heights), rel=1e-3)
    for i in range(5):
        depth = np.load(out / "ride" / f"f{i}.npy")
        fitted = float(ground_height(torch.from_numpy(depth)[None, None], cam)[0])
        assert fitted == pytest.approx(heights[i] * scale["factor"], rel=1e-3)  # one factor, not per frame
    # the median frame's ground lies 1.6 m below
    fits = sorted(
        float(ground_height(torch.from_numpy(np.load(f))[None, None], cam)[0])
        for f in sorted((out / "ride").glob("*.npy"))
    )
    assert fits[2] == pytest.approx(1.6, rel=1e-3) and fits[0] < 1.6 < fits[-1]
