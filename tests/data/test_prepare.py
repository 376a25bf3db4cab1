"""``cylsfm prepare equirect`` / ``frames``: equirectangular footage into cylindrical sequences that match the
direct cylindrical render, resumable and idempotent, honest about broken videos, and ``cylsfm split``'s
rule applied to what it wrote."""

from __future__ import annotations

import json
import math

import av
import numpy as np
import pytest
import torch

from cylsfm.cli import main
from cylsfm.data.format import load_image, scan_dataset
from cylsfm.data.io import save_png
from cylsfm.data.prepare import EquirectOptions, prepare_equirect
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera, EquirectangularCamera, inverse_warp, invert

N = 5
OUT_W, OUT_H = 128, 32


def _poses() -> list[torch.Tensor]:
    return [make_pose(0.5 - 0.1 * i, 0.1, -1.5 + 0.25 * i, yaw_deg=5.0 * i) for i in range(N)]


def _u8(image: torch.Tensor) -> np.ndarray:
    return (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Equirectangular frames (a folder and a lossless video) and the direct cylindrical renders."""
    root = tmp_path_factory.mktemp("scene")
    eq_cam = EquirectangularCamera.full(512, 256)
    cyl_cam = CylindricalCamera.full(OUT_W, OUT_H)
    folder = root / "ride"
    folder.mkdir()
    frames, direct, depth = [], [], []
    for i, c2w in enumerate(_poses()):
        frames.append(_u8(render_room(eq_cam, c2w, supersample=2)[0]))
        save_png(folder / f"frame{i:03d}.png", frames[-1])
        image, d = render_room(cyl_cam, c2w, supersample=4)
        direct.append(_u8(image))
        depth.append(d)
    video = root / "ride.mkv"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("ffv1", rate=5)
        stream.width, stream.height, stream.pix_fmt = 512, 256, "bgr0"
        for f in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    return {"folder": folder, "video": video, "direct": direct, "depth": depth, "camera": cyl_cam}


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * math.log10(255.0**2 / max(mse, 1e-12))


def _options(**kw) -> EquirectOptions:
    return EquirectOptions(size=(OUT_W, OUT_H), **kw)


@pytest.mark.parametrize("kind", ["folder", "video"])
def test_equirect_input_gives_the_direct_cylindrical_render(scene, tmp_path, kind):
    reports = prepare_equirect([scene[kind]], tmp_path / "data", _options(), progress=False)
    assert reports[0].written == N and reports[0].broke_off is None
    seq = scan_dataset(tmp_path / "data")[0]
    assert seq.camera.to_dict() == scene["camera"].to_dict()
    for path, direct in zip(seq.images, scene["direct"], strict=True):
        assert _psnr(load_image(path), direct) >= 30.0
    # the written intrinsics make inverse_warp with true depth and pose reproduce the target
    images = [
        torch.from_numpy(np.array(load_image(p))).permute(2, 0, 1)[None].float() / 255 for p in seq.images
    ]
    poses = _poses()
    rel = invert(poses[1]) @ poses[0]  # target 0 -> source 1
    warped, valid = inverse_warp(images[1], scene["depth"][0], rel[None].float(), seq.camera)
    err = ((warped - images[0]).abs() * valid).sum() / valid.sum() / 3
    assert valid.float().mean() > 0.8 and float(err) < 0.04


def test_resume_idempotence_and_settings(scene, tmp_path):
    out = tmp_path / "data"
    prepare_equirect([scene["folder"]], out, _options(), progress=False)
    seq_dir = out / "ride"
    stamps = {p.name: p.stat().st_mtime_ns for p in (seq_dir / "images").iterdir()}
    again = prepare_equirect([scene["folder"]], out, _options(), progress=False)
    assert (
        again[0].skipped and {p.name: p.stat().st_mtime_ns for p in (seq_dir / "images").iterdir()} == stamps
    )
    # an interrupted run (camera.json not yet written, two frames missing) continues
    (seq_dir / "camera.json").unlink()
    record = json.loads((seq_dir / "prepare.json").read_text())
    record["finished"] = False
    (seq_dir / "prepare.json").write_text(json.dumps(record))
    for name in sorted(stamps)[-2:]:
        (seq_dir / "images" / name).unlink()
    resumed = prepare_equirect([scene["folder"]], out, _options(), progress=False)
    assert not resumed[0].skipped and resumed[0].written == N
    kept = sorted(stamps)[:-2]
    assert all((seq_dir / "images" / n).stat().st_mtime_ns == stamps[n] for n in kept)
    with pytest.raises(CylsfmError, match="other settings"):
        prepare_equirect([scene["folder"]], out, _options(fps=2.0), progress=False)
    prepare_equirect(
        [scene["folder"]], out, _options(exclude=frozenset({"frame002"})), overwrite=True, progress=False
    )
    assert sorted(p.stem for p in (seq_dir / "images").iterdir()) == [
        "frame000",
        "frame001",
        "frame003",
        "frame004",
    ]


def test_a_video_that_breaks_off_keeps_its_frames_and_says_so(scene, tmp_path):
    data = scene["video"].read_bytes()
    broken = tmp_path / "broken.mkv"
    broken.write_bytes(data[: int(len(data) * 0.6)])
    report = prepare_equirect([broken], tmp_path / "data", _options(), progress=False)[0]
    assert 1 <= report.written < N and report.broke_off
    assert f"of {N}" in report.line() and "breaks off" in report.line()
    record = json.loads((tmp_path / "data" / "broken" / "prepare.json").read_text())
    assert record["frames_announced"] == N and record["frames_decoded"] < N and record["broke_off"]


def test_bad_inputs_are_one_line_errors(scene, tmp_path, capsys):
    wide = tmp_path / "wide"
    wide.mkdir()
    save_png(wide / "a.png", np.zeros((100, 300, 3), np.uint8))
    save_png(wide / "b.png", np.zeros((100, 300, 3), np.uint8))
    assert main(["prepare", "equirect", str(wide), str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert str(wide) in err and "twice the height" in err and err.count("\n") == 1
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\x00" * 300)
    assert main(["prepare", "equirect", str(junk), str(tmp_path / "o"), "--no-progress"]) == 2
    assert str(junk) in capsys.readouterr().err
    mask = tmp_path / "mask.png"
    save_png(mask, np.zeros((10, 30), np.uint8))
    args = ["prepare", "equirect", str(scene["folder"]), str(tmp_path / "o"), "--size", "128x32"]
    assert main([*args, "--mask", str(mask), "--no-progress"]) == 2
    assert str(mask) in capsys.readouterr().err


def test_cli_mask_frames_and_splits(scene, tmp_path, capsys):
    out = tmp_path / "data"
    mask = np.full((256, 512), 255, np.uint8)
    mask[200:] = 0  # the helmet: the bottom of the sphere
    save_png(tmp_path / "helmet.png", mask)
    args = ["prepare", "equirect", str(scene["folder"]), str(scene["video"]), str(out), "--size", "128x32"]
    assert main([*args, "--mask", str(tmp_path / "helmet.png"), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "ride: 5 frames" in printed and "by frame" in printed
    written = np.asarray(load_image(out / "ride" / "mask.png"))[..., 0] > 127
    # elevation of row v: atan(h), h = (v - cy) / fy; the mask starts at 200/256 of the sphere: 50.6 deg
    cam = scene["camera"]
    elev = np.degrees(np.arctan((np.arange(OUT_H) - float(cam.cy)) / float(cam.fy)))
    assert written[elev < 40].all() and not written[elev > 60].any()
    assert (out / "splits" / "default" / "test.txt").is_file()
    # cylindrical frames as they are
    frames_out = tmp_path / "frames"
    cam.to_json(tmp_path / "cyl.json")
    assert (
        main(
            [
                "prepare",
                "frames",
                str(out / "ride" / "images"),
                str(frames_out),
                "--camera",
                str(tmp_path / "cyl.json"),
                "--no-progress",
                "--split",
                "none",
            ]
        )
        == 0
    )
    seq = scan_dataset(frames_out)[0]
    assert len(seq.images) == N and not (frames_out / "splits").exists()
    assert (
        main(
            [
                "prepare",
                "frames",
                str(scene["folder"]),
                str(tmp_path / "f2"),
                "--camera",
                str(tmp_path / "cyl.json"),
                "--no-progress",
            ]
        )
        == 2
    )
    assert "512x256" in capsys.readouterr().err


def test_a_size_that_training_refuses_is_warned_about(scene, tmp_path, capsys):
    """Panoramas 200 px wide are written, with a warning: full panoramas train at multiples of 128."""
    out = tmp_path / "odd"
    args = ["prepare", "equirect", str(scene["folder"]), str(out), "--no-progress"]
    assert main([*args, "--size", "200x50"]) == 0
    err = capsys.readouterr().err
    assert "200x50" in err and "multiple of 128" in err and "cylsfm train refuses" in err
    assert main([*args[:3], str(tmp_path / "fine"), "--no-progress", "--size", "128x32"]) == 0
    assert "refuses" not in capsys.readouterr().err


def test_sigterm_stops_prepare_like_ctrl_c_and_the_run_continues(scene, tmp_path, monkeypatch, capsys):
    """SIGTERM after the third frame of a video: exit status 143 with one line, the frames written so far
    kept, and the same command then finishes a dataset identical, byte for byte, to an uninterrupted one,
    writing only the frames that were missing (those on disk are not written again).

    The frames are converted one at a time here (not 8 at once), so that some are on disk when the signal
    comes."""
    import dataclasses
    import os
    import signal

    from cylsfm.data.prepare import equirect

    init = equirect._Converter.__init__

    def one_at_a_time(self, seq, resample, options):
        init(self, seq, resample, dataclasses.replace(options, batch=1))

    monkeypatch.setattr(equirect._Converter, "__init__", one_at_a_time)
    args = ["prepare", "equirect", str(scene["video"]), "--size", "128x32", "--no-progress"]
    assert main([*args, str(tmp_path / "whole")]) == 0
    add, calls = equirect._Converter.add, {"n": 0}

    def signalled_add(self, name, rgb):
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return add(self, name, rgb)

    monkeypatch.setattr(equirect._Converter, "add", signalled_add)
    capsys.readouterr()
    assert main([*args, str(tmp_path / "cut")]) == 143
    assert "interrupted by SIGTERM" in capsys.readouterr().err
    monkeypatch.setattr(equirect._Converter, "add", add)
    kept = {  # the frames written before the signal, as files: these must not be written again
        p.relative_to(tmp_path / "cut"): (p.stat().st_ino, p.stat().st_mtime_ns)
        for p in (tmp_path / "cut").rglob("images/*.png")
    }
    assert len(kept) >= 2
    from cylsfm.data.prepare.sequence import PreparedSequence

    write, written = PreparedSequence.add, []

    def recorded_write(self, frame, *a, **k):
        written.append(frame)
        return write(self, frame, *a, **k)

    monkeypatch.setattr(PreparedSequence, "add", recorded_write)
    assert main([*args, str(tmp_path / "cut")]) == 0
    monkeypatch.setattr(PreparedSequence, "add", write)
    again = sorted({rel.stem for rel in kept} & set(written))
    assert not again, f"the resumed run wrote again the frames {again} written before SIGTERM"
    for rel, (inode, mtime) in kept.items():
        stat = (tmp_path / "cut" / rel).stat()
        assert (stat.st_ino, stat.st_mtime_ns) == (inode, mtime), f"{rel} was written again"
    whole = sorted(p.relative_to(tmp_path / "whole") for p in (tmp_path / "whole").rglob("*.png"))
    cut = sorted(p.relative_to(tmp_path / "cut") for p in (tmp_path / "cut").rglob("*.png"))
    assert whole == cut and len(whole) >= 4
    assert sorted(written) == sorted(
        rel.stem for rel in whole if rel not in kept and rel.parent.name == "images"
    )
    for rel in whole:
        assert (tmp_path / "whole" / rel).read_bytes() == (tmp_path / "cut" / rel).read_bytes(), rel
