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


def test_sparse_points_are_logged_once_for_the_whole_ride(tmp_path, monkeypatch):
    from cylsfm.export.rerun import RerunWriter

    logged = {}
    real_log = rr.RecordingStream.log

    def log(self, path, entity, *a, **k):
        logged.setdefault(path, []).append((entity, k.get("static")))
        return real_log(self, path, entity, *a, **k)

    monkeypatch.setattr(rr.RecordingStream, "log", log)
    writer = RerunWriter(tmp_path / "r.rrd")
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    writer.add_points(xyz, np.array([[255, 0, 0], [0, 255, 0]], np.uint8))
    cam = CylindricalCamera.full(64, 16)
    writer.add(
        0,
        0.0,
        np.zeros((16, 64, 3), np.uint8),
        np.eye(4),
        np.ones((16, 64)),
        cam,
        np.zeros((16, 64, 3), np.uint8),
    )
    writer.finish()
    ((entity, static),) = logged["world/points"]
    assert static
    np.testing.assert_allclose(entity.positions.as_arrow_array().to_pylist(), xyz)
    assert _rerun("rrd", "verify", str(tmp_path / "r.rrd")).returncode == 0


def _logged_camera_poses(recording) -> dict[int, np.ndarray]:
    """Frame index -> the 4x4 transform stored for ``/world/camera`` in a recording file, read back."""
    from rerun.chunk import RrdReader

    poses = {}
    for chunk in RrdReader(recording).stream():
        if chunk.entity_path != "/world/camera":
            continue
        for row in chunk.to_record_batch().to_pylist():
            relation = row.get("Transform3D:relation")
            assert not relation or "ChildFromParent" not in str(relation), relation
            pose = np.eye(4)
            # rerun keeps a 3x3 matrix column after column
            pose[:3, :3] = np.asarray(row["Transform3D:mat3x3"][0]).reshape(3, 3, order="F")
            pose[:3, 3] = row["Transform3D:translation"][0]
            poses[row["frame"]] = pose
    return poses


def test_the_camera_entity_holds_the_camera_to_world_pose(tmp_path):
    """What the recording stores for ``world/camera`` at each frame is the camera-to-world pose given (rerun's
    parent-from-child), not its inverse, and the trajectory runs through the cameras' centres."""
    from rerun.chunk import RrdReader

    from cylsfm.export.rerun import RerunWriter
    from cylsfm.geometry.pose import rotation_x, rotation_y, rotation_z

    cam = CylindricalCamera.full(64, 16)
    depth = np.full((16, 64), 2.0, np.float32)
    blank = np.zeros((16, 64, 3), np.uint8)
    given = {}
    writer = RerunWriter(tmp_path / "r.rrd", points_per_frame=50)
    for index, (yaw, pitch, roll, centre) in enumerate(
        [(0.7, 0.2, -0.1, (1.5, -0.3, 2.0)), (-1.2, -0.15, 0.25, (-0.5, 0.4, 3.5))]
    ):
        c2w = np.eye(4)
        c2w[:3, :3] = rotation_y(np.array(yaw)) @ rotation_x(np.array(pitch)) @ rotation_z(np.array(roll))
        c2w[:3, 3] = centre
        given[index] = c2w
        writer.add(index, 0.1 * index, blank, c2w, depth, cam, blank)
    writer.finish()

    logged = _logged_camera_poses(tmp_path / "r.rrd")
    assert sorted(logged) == sorted(given)
    for index, c2w in given.items():
        np.testing.assert_allclose(
            logged[index], c2w, atol=1e-6, err_msg=f"frame {index}: not the camera-to-world pose"
        )
    (trajectory,) = [
        row["LineStrips3D:strips"][0]
        for chunk in RrdReader(tmp_path / "r.rrd").stream()
        if chunk.entity_path == "/world/trajectory"
        for row in chunk.to_record_batch().to_pylist()
    ]
    np.testing.assert_allclose(trajectory, [given[i][:3, 3] for i in sorted(given)], atol=1e-6)
