"""Finding the direction of travel in the panorama (a camera mounted turned) from images and depth alone."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

import cylsfm
from cylsfm.data.format import SequenceWriter
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.geometry import CylindricalCamera, roll_columns
from cylsfm.odometry import OdometrySettings
from cylsfm.odometry.mount import mount_yaw

W, H, N = 128, 32, 10


def _travel_deg(i: int) -> float:
    """The true azimuth of the travel from frame i, in frame i's camera (the ride below)."""
    return math.degrees(math.atan2(-0.12, 0.3)) - (-8.0 + 3.0 * i)


@pytest.fixture(scope="module")
def frames():
    cam = CylindricalCamera.full(W, H)
    images, depths, poses = [], [], []
    for i in range(N):
        c2w = make_pose(0.8 - 0.12 * i, 0.1, -2.0 + 0.3 * i, yaw_deg=-8.0 + 3.0 * i)
        image, depth = render_room(cam, c2w, supersample=2)
        images.append(image[0].clamp(0, 1))
        depths.append(depth[0])
        poses.append(c2w.numpy())
    return cam, torch.stack(images), torch.stack(depths), np.stack(poses)


def _wrapped(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize("roll", [0, 32, 77, 100])
def test_the_direction_of_travel_is_found_however_the_camera_is_mounted(frames, roll):
    cam, images, depth, _ = frames
    found = mount_yaw(roll_columns(images, roll), roll_columns(depth, roll), cam, step_length=0.3)
    assert found is not None and found.pairs == N - 3 and found.agreement > 0.8
    turned = 360.0 * roll / W
    lo, hi = _travel_deg(N - 4), _travel_deg(0)  # the pairs' own directions (the camera turns)
    assert lo - 3 <= _wrapped(math.degrees(found.yaw) - turned) <= hi + 3


@pytest.mark.parametrize("roll", [0, 77])
def test_the_search_at_half_size_finds_the_direction_of_the_search_at_full_size(frames, roll):
    cam, images, depth, _ = frames
    args = (roll_columns(images, roll), roll_columns(depth, roll), cam)
    fast = mount_yaw(*args, step_length=0.3)
    full = mount_yaw(*args, step_length=0.3, halve=False)
    assert fast is not None and full is not None and fast.pairs == full.pairs
    assert abs(_wrapped(math.degrees(fast.yaw - full.yaw))) < 1.5
    assert fast.agreement == pytest.approx(full.agreement, abs=0.1)


def test_too_few_frames_give_no_direction(frames):
    cam, images, depth, _ = frames
    assert mount_yaw(images[:3], depth[:3], cam, step_length=0.3) is None


def test_odometry_turns_the_network_to_the_direction_found_and_says_so(frames, ckpt, tmp_path):

    cam, images, depth, poses = frames
    seq = tmp_path / "data" / "ride"
    writer = SequenceWriter(seq, cam)
    for im, d in zip(roll_columns(images, 77), roll_columns(depth, 77), strict=True):
        writer.add_frame((im.permute(1, 2, 0) * 255).round().byte().numpy(), d[0].numpy())
    writer.finish(poses, timestamps=np.arange(N) * 0.2)
    out = tmp_path / "o"
    settings = OdometrySettings(refine=True, depth_from=tmp_path / "data", device="cpu", progress=False)
    cylsfm.odometry(seq, ckpt, out, settings)
    summary = json.loads((out / "odometry.json").read_text())["direction_of_travel"]
    assert summary["pairs"] > 0 and "found" in summary["how"]
    assert abs(_wrapped(summary["yaw_deg"] - 360.0 * 77 / W - _travel_deg(3))) < 12
    assert "direction of travel" in (out / "trajectory.txt").read_text()
    given = cylsfm.odometry(
        seq, ckpt, tmp_path / "g", OdometrySettings(mount_yaw=90.0, device="cpu", progress=False)
    )
    text = given.trajectory.read_text()
    assert "90.0 deg (given)" in text
