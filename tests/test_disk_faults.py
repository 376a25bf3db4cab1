"""Every writing command on a full disk (ENOSPC) and in a read-only directory (EROFS): exit status 2 with one
line naming the file, the previous file intact, no temporary file left behind, and (for the long commands)
the same command continuing once the disk has room. Writers: the prepared frame, the odometry state, the
PLY mesh, the stereo frame and the ONNX model (the checkpoint: tests/train/test_write_faults.py)."""

from __future__ import annotations

import errno

import av
import numpy as np
import pytest

from cylsfm.cli import main
from cylsfm.data.io import save_png
from cylsfm.data.synth import generate_dataset
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.errors import CylsfmError
from cylsfm.geometry import EquirectangularCamera
from helpers import failing_writes, untrained_checkpoint

FAULTS = [(errno.ENOSPC, "No space left on device"), (errno.EROFS, "Read-only file system")]
IDS = ["full-disk", "read-only"]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    return untrained_checkpoint(tmp_path_factory.mktemp("ckpt"))


@pytest.fixture(scope="module")
def pano(tmp_path_factory):
    root = tmp_path_factory.mktemp("pano")
    generate_dataset(root, sequences=1, frames=10, width=128, height=32, seed=2, workers=1, progress=False)
    return root / "seq_000"


def _failed(capsys, name: str, reason: str) -> None:
    err = capsys.readouterr().err
    assert f"{name}: cannot write ({reason})" in err and err.count("\n") == 1, err
    assert "Traceback" not in err


def _no_temporaries(folder) -> None:
    assert not [p for p in folder.rglob(".*.tmp")], list(folder.rglob(".*.tmp"))


@pytest.mark.parametrize(("error", "reason"), FAULTS, ids=IDS)
def test_export_mesh_keeps_the_previous_ply(pano, ckpt, tmp_path, monkeypatch, capsys, error, reason):
    out = tmp_path / "mesh.ply"
    args = ["export", "mesh", str(pano / "images" / "000000.png"), str(out), "--device", "cpu"]
    assert main([*args, "--checkpoint", str(ckpt)]) == 0
    before = out.read_bytes()
    failing_writes(monkeypatch, "mesh.ply", error)
    capsys.readouterr()
    assert main([*args, "--depth", str(pano / "depth" / "000000.npy")]) == 2
    _failed(capsys, "mesh.ply", reason)
    assert out.read_bytes() == before
    _no_temporaries(tmp_path)


@pytest.mark.parametrize(("error", "reason"), FAULTS, ids=IDS)
def test_export_stereo_keeps_the_previous_frame(pano, tmp_path, monkeypatch, capsys, error, reason):
    out = tmp_path / "pair.png"
    args = ["export", "stereo", str(pano / "images" / "000000.png"), str(out)]
    assert main([*args, "--depth", str(pano / "depth" / "000000.npy")]) == 0
    before = out.read_bytes()
    failing_writes(monkeypatch, "pair.png", error)
    capsys.readouterr()
    assert main([*args, "--depth", str(pano / "depth" / "000001.npy")]) == 2
    _failed(capsys, "pair.png", reason)
    assert out.read_bytes() == before
    _no_temporaries(tmp_path)


@pytest.mark.parametrize(("error", "reason"), FAULTS, ids=IDS)
def test_export_onnx_keeps_the_previous_model(ckpt, tmp_path, monkeypatch, capsys, error, reason):
    out = tmp_path / "depth.onnx"
    out.write_bytes(b"an earlier model")
    failing_writes(monkeypatch, "depth.onnx", error)
    assert main(["export", "onnx", "--checkpoint", str(ckpt), "--out", str(out), "--no-check"]) == 2
    _failed(capsys, "depth.onnx", reason)
    assert out.read_bytes() == b"an earlier model"
    _no_temporaries(tmp_path)


@pytest.mark.parametrize(("error", "reason"), FAULTS, ids=IDS)
def test_odometry_keeps_its_last_state_and_continues(
    pano, ckpt, tmp_path, monkeypatch, capsys, error, reason
):
    from cylsfm.odometry import track as odometry_track
    from cylsfm.odometry.state import STATE_FILE, State

    monkeypatch.setattr(odometry_track, "CHUNK", 4)
    args = ["odometry", str(pano), "--checkpoint", str(ckpt), "--device", "cpu", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    out = tmp_path / "cut"
    saves, save = {"n": 0}, State.save

    def failing_after_one(self, path):
        saves["n"] += 1
        if saves["n"] == 2:
            failing_writes(monkeypatch, STATE_FILE, error)
        return save(self, path)

    monkeypatch.setattr(State, "save", failing_after_one)
    capsys.readouterr()
    assert main([*args, "--out", str(out)]) == 2
    _failed(capsys, STATE_FILE, reason)
    monkeypatch.undo()
    with np.load(out / STATE_FILE) as kept:  # the first chunk's state, whole
        assert len(kept["stems"]) == 4 and not bool(kept["finished"])
    _no_temporaries(out)
    assert main([*args, "--out", str(out)]) == 0  # the disk has room again: it continues
    np.testing.assert_allclose(
        np.loadtxt(out / "trajectory.txt"), np.loadtxt(tmp_path / "whole" / "trajectory.txt"), atol=1e-6
    )


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    root = tmp_path_factory.mktemp("video")
    path = root / "ride.mkv"
    cam = EquirectangularCamera.full(256, 128)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=5)
        stream.width, stream.height, stream.pix_fmt = 256, 128, "bgr0"
        for i in range(6):
            image, _ = render_room(cam, make_pose(0.1 * i, 0.0, 0.2 * i, yaw_deg=3.0 * i))
            frame = (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    return path


@pytest.mark.parametrize(("error", "reason"), FAULTS, ids=IDS)
def test_prepare_stops_at_the_frame_it_cannot_write_and_continues(
    video, tmp_path, monkeypatch, capsys, error, reason
):
    args = ["prepare", "equirect", str(video), "--size", "128x32", "--no-progress"]
    assert main([*args, str(tmp_path / "whole")]) == 0
    failing_writes(monkeypatch, "000003.png", error)
    capsys.readouterr()
    out = tmp_path / "cut"
    assert main([*args, str(out)]) == 2
    err = capsys.readouterr().err  # (PNGs are written by threads: other frames may have been in flight)
    assert f"000003.png: cannot write ({reason})" in err and "Traceback" not in err, err
    written = sorted(p.name for p in out.rglob("images/*.png"))
    assert "000003.png" not in written
    _no_temporaries(out)
    monkeypatch.undo()
    assert main([*args, str(out)]) == 0
    whole = sorted(p.relative_to(tmp_path / "whole") for p in (tmp_path / "whole").rglob("*.png"))
    assert sorted(p.relative_to(out) for p in out.rglob("*.png")) == whole
    for rel in whole:
        assert (out / rel).read_bytes() == (tmp_path / "whole" / rel).read_bytes(), rel


def test_the_helper_fails_only_the_named_file(tmp_path, monkeypatch):
    failing_writes(monkeypatch, "a.png", errno.ENOSPC)
    save_png(tmp_path / "b.png", np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(CylsfmError, match=r"a\.png: cannot write"):
        save_png(tmp_path / "a.png", np.zeros((2, 2, 3), np.uint8))


def test_written_files_get_the_permissions_of_a_plain_open(tmp_path):
    """Not the temporary file's private 0o600: a viewer's folder is meant to be served, frames shared."""
    import os

    from cylsfm.atomic import atomic_write_text

    mask = os.umask(0o022)
    os.umask(mask)
    atomic_write_text(tmp_path / "a.txt", "x")
    (tmp_path / "b.txt").write_text("x")
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == (tmp_path / "b.txt").stat().st_mode & 0o777
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o666 & ~mask
