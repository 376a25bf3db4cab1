"""``cylsfm export rerun``: a ride as a rerun recording, checked with rerun's own ``rrd verify`` and by what
was logged (the points are the panorama's own back-projection, not a pinhole model's)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from cylsfm.cli import main
from cylsfm.data.synth import generate_dataset
from cylsfm.geometry import CylindricalCamera
from helpers import untrained_checkpoint

rr = pytest.importorskip("rerun")


def _rerun(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rerun", *args], capture_output=True, text=True, timeout=120)


def test_a_ride_becomes_a_recording_that_rerun_verifies(tmp_path):
    generate_dataset(
        tmp_path / "data", sequences=1, frames=6, width=128, height=32, seed=6, workers=1, progress=False
    )
    ckpt = untrained_checkpoint(tmp_path)
    out = tmp_path / "ride.rrd"
    args = ["export", "rerun", str(tmp_path / "data" / "seq_000"), str(out), "--checkpoint", str(ckpt)]
    assert main([*args, "--device", "cpu", "--no-progress"]) == 0
    assert _rerun("rrd", "verify", str(out)).returncode == 0
    printed = _rerun("rrd", "print", str(out)).stdout
    for entity in ("world/camera", "world/camera/points", "world/trajectory", "panorama", "depth"):
        assert f"/{entity}" in printed or entity in printed, entity
    assert not list(tmp_path.glob(".*.tmp"))
    assert (tmp_path / "ride.rrd.odometry" / "trajectory.txt").is_file()


def test_the_points_are_the_panoramas_back_projection(tmp_path, monkeypatch):
    from cylsfm.export.rerun import RerunWriter

    logged = {}
    real_log = rr.RecordingStream.log

    def log(self, path, entity, *a, **k):
        logged.setdefault(path, []).append(entity)
        return real_log(self, path, entity, *a, **k)

    monkeypatch.setattr(rr.RecordingStream, "log", log)
    cam = CylindricalCamera.full(64, 16)
    depth = np.full((16, 64), 2.0, np.float32)
    depth[:, :8] = 0  # unknown: no points
    colours = np.zeros((16, 64, 3), np.uint8)
    writer = RerunWriter(tmp_path / "r.rrd", points_per_frame=10_000)
    writer.add(0, 0.0, np.zeros((16, 64, 3), np.uint8), np.eye(4), depth, cam, colours)
    writer.finish()
    points = np.asarray(logged["world/camera/points"][0].positions.as_arrow_array().to_pylist())
    assert len(points) == 16 * 56
    horizontal = np.hypot(points[:, 0], points[:, 2])  # cylindrical depth: the horizontal distance
    np.testing.assert_allclose(horizontal, 2.0, rtol=1e-5)
    theta = np.arctan2(points[:, 0], points[:, 2])  # columns 8..63: theta = (u - W/2) 2 pi / W
    assert theta.min() == pytest.approx((8 - 32) * 2 * math.pi / 64, abs=1e-5)
    assert _rerun("rrd", "verify", str(tmp_path / "r.rrd")).returncode == 0
