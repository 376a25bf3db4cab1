"""``cylsfm odometry`` end to end on a small rendered ride: the trajectory file (through evo), ground-truth
depth refinement, metres from the camera height, resuming a killed run, videos, and bad inputs."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import av
import numpy as np
import pytest
import torch

import cylsfm
from cylsfm.cli import main
from cylsfm.data.format import SequenceWriter, load_image
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.geometry import CylindricalCamera, rotation_y
from cylsfm.odometry import OdometrySettings
from cylsfm.odometry import track as odometry_track
from cylsfm.odometry.track import Tracker, keyframe_steps

N_FRAMES = 10


@pytest.fixture(scope="module")
def ride(tmp_path_factory) -> Path:
    """A dataset sequence: a camera driving and turning through the room, 128x32, with depth and poses."""
    poses = [make_pose(0.8 - 0.12 * i, 0.1, -2.0 + 0.3 * i, yaw_deg=-8.0 + 3.0 * i) for i in range(N_FRAMES)]
    return _room_ride(tmp_path_factory.mktemp("data") / "ride", poses)


def _room_ride(seq: Path, poses: list) -> Path:
    """The room seen from camera-to-world ``poses`` at 128x32, written as a dataset sequence (5 fps)."""
    cam = CylindricalCamera.full(128, 32)
    writer = SequenceWriter(seq, cam)
    for c2w in poses:
        image, depth = render_room(cam, c2w, supersample=2)
        rgb = (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()
        writer.add_frame(rgb, depth[0, 0].numpy())
    return writer.finish(np.stack([c.numpy() for c in poses]), timestamps=np.arange(len(poses)) * 0.2)


def _run(ckpt, *args) -> int:
    return main(["odometry", "--checkpoint", str(ckpt), "--device", "cpu", "--no-progress", *map(str, args)])


def test_refined_with_true_depth_recovers_the_ride(ckpt, ride, tmp_path, capsys):
    out = tmp_path / "out"
    assert _run(ckpt, ride, "--out", out, "--refine", "--depth-from", ride.parent) == 0
    printed = capsys.readouterr().out
    assert "refined" in printed and "constant_velocity" in printed
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(out / "trajectory.txt"))
    assert traj.num_poses == N_FRAMES
    np.testing.assert_allclose(traj.timestamps, np.arange(N_FRAMES) * 0.2)
    header = (out / "trajectory.txt").read_text().splitlines()[1]
    assert "metres (ground-truth depth)" in header
    metrics = __import__("json").loads((out / "metrics.json").read_text())
    assert metrics["refined"]["rot_err_deg_mean"] < 0.2
    assert metrics["refined"]["dir_err_deg_mean"] < 3.0
    # metres: the unaligned refined path has the true length within a few percent
    gt = np.stack([make_pose(0.8 - 0.12 * i, 0.1, -2.0 + 0.3 * i).numpy() for i in range(N_FRAMES)])
    est = np.stack(traj.poses_se3)
    true_len = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    est_len = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1).sum()
    assert est_len == pytest.approx(true_len, rel=0.05)
    assert metrics["refined"]["rot_err_deg_mean"] < metrics["network"]["rot_err_deg_mean"]
    assert (out / "trajectory.png").stat().st_size > 1000
    assert (out / "trajectory_network.txt").is_file()


def test_library_call_and_metres_from_the_camera_height(ckpt, ride, tmp_path):
    result = cylsfm.odometry(
        ride,
        ckpt,
        tmp_path / "o",
        OdometrySettings(camera_height=1.5, save_depth_maps=True, device="cpu", progress=False),
    )
    assert result.unit == "metres" and result.metres_per_unit > 0
    assert "camera height 1.5 m" in (tmp_path / "o" / "trajectory.txt").read_text()
    depth = np.load(tmp_path / "o" / "depth" / f"{result.frames[3]}.npy")
    assert depth.shape == (32, 128)
    assert not (tmp_path / "o" / odometry_track.RAW_DEPTH).exists()
    assert len(result.c2w) == N_FRAMES and result.metrics is not None


def test_steady_height_changes_the_lengths_only(ckpt, ride, tmp_path):
    opt = OdometrySettings(refine=True, device="cpu", progress=False, loops=False, bundle=False)
    plain = cylsfm.odometry(ride, ckpt, tmp_path / "plain", opt)
    steady = cylsfm.odometry(ride, ckpt, tmp_path / "steady", replace(opt, steady_height=True))
    assert "steady camera height" in (tmp_path / "steady" / "trajectory.txt").read_text()
    assert json.loads((tmp_path / "steady" / "odometry.json").read_text())["steady_height"] is True
    rel = [np.linalg.inv(r.c2w[:-1]) @ r.c2w[1:] for r in (plain, steady)]
    np.testing.assert_allclose(rel[0][:, :3, :3], rel[1][:, :3, :3], atol=1e-9)  # same rotations
    lengths = [np.linalg.norm(r[:, :3, 3], axis=1) for r in rel]
    assert not np.allclose(lengths[0], lengths[1])
    # directions kept: each step's translation is the plain one times a positive factor
    cos = (rel[0][:, :3, 3] * rel[1][:, :3, 3]).sum(1) / (lengths[0] * lengths[1])
    assert (cos > 1 - 1e-9).all()
    # measured: the refinement as it was, and the trajectory written beside it
    assert "steady height" not in plain.metrics and "steady height" in steady.metrics
    assert steady.metrics["refined"] == plain.metrics["refined"]
    assert steady.metrics["steady height"]["n_frames"] == plain.metrics["refined"]["n_frames"]
    assert steady.metrics["steady height"] != plain.metrics["refined"]


def test_a_killed_run_continues_to_the_same_trajectory(ckpt, ride, tmp_path, monkeypatch):
    monkeypatch.setattr(odometry_track, "CHUNK", 3)
    whole = cylsfm.odometry(
        ride, ckpt, tmp_path / "whole", OdometrySettings(refine=True, device="cpu", progress=False)
    )
    push = Tracker.push
    calls = {"n": 0}

    def dying_push(self, indices, images):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return push(self, indices, images)

    monkeypatch.setattr(Tracker, "push", dying_push)
    with pytest.raises(KeyboardInterrupt):
        cylsfm.odometry(
            ride, ckpt, tmp_path / "killed", OdometrySettings(refine=True, device="cpu", progress=False)
        )
    assert not (tmp_path / "killed" / "trajectory.txt").exists()
    with np.load(
        tmp_path / "killed" / odometry_track.STATE_FILE
    ) as saved:  # two chunks of 3 frames were done
        assert len(saved["stems"]) == 6 and not bool(saved["finished"])
    # the work done on resuming: the frames after the saved ones pushed and their depth predicted, once each
    pushed: list[list[int]] = []
    depth_frames: list[int] = []
    depth = odometry_track.Predictor.depth

    def recording_push(self, indices, images):
        pushed.append(list(indices))
        return push(self, indices, images)

    def counting_depth(self, images, camera):
        depth_frames.append(int(images.shape[0]))
        return depth(self, images, camera)

    monkeypatch.setattr(Tracker, "push", recording_push)
    monkeypatch.setattr(odometry_track.Predictor, "depth", counting_depth)
    resumed = cylsfm.odometry(
        ride, ckpt, tmp_path / "killed", OdometrySettings(refine=True, device="cpu", progress=False)
    )
    np.testing.assert_allclose(resumed.c2w, whole.c2w, atol=1e-6)
    assert pushed == [[6, 7, 8], [9]]  # the first chunks were not redone
    assert sum(depth_frames) == N_FRAMES - 6


def test_a_video_ride(ckpt, ride, tmp_path):
    video = tmp_path / "ride.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("mpeg4", rate=5)
        stream.width, stream.height, stream.pix_fmt = 128, 32, "yuv420p"
        for f in sorted((ride / "images").iterdir()):
            from PIL import Image

            frame = av.VideoFrame.from_ndarray(np.asarray(Image.open(f).convert("RGB")), format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    result = cylsfm.odometry(
        video, ckpt, tmp_path / "v", OdometrySettings(refine=True, device="cpu", progress=False)
    )
    assert len(result.c2w) == N_FRAMES
    np.testing.assert_allclose(result.times, np.arange(N_FRAMES) / 5, atol=1e-6)
    assert result.metrics is None
    # the frames come in the video's order: each decoded frame is nearest its own source image
    from cylsfm.odometry import open_ride

    sources = np.stack([load_image(f) for f in sorted((ride / "images").iterdir())]).astype(np.float32)
    decoded = [(i, rgb) for i, _, _, rgb in open_ride(video).read()]
    assert [i for i, _ in decoded] == list(range(N_FRAMES))
    nearest = [
        int(np.abs(sources - rgb.astype(np.float32)).mean(axis=(1, 2, 3)).argmin()) for _, rgb in decoded
    ]
    assert nearest == list(range(N_FRAMES)), nearest
    rot = np.degrees(np.arctan2(result.c2w[-1, 0, 2], result.c2w[-1, 2, 2]))
    assert math.isfinite(rot)


def test_bad_inputs_are_one_line_errors_naming_the_file(ckpt, ride, tmp_path, capsys):
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00not a video at all" * 50)
    assert _run(ckpt, broken, "--out", tmp_path / "a") == 2
    assert str(broken) in capsys.readouterr().err
    wrong = tmp_path / "camera.json"
    CylindricalCamera.full(100, 50).to_json(wrong)
    assert _run(ckpt, ride, "--out", tmp_path / "b", "--camera", wrong) == 2
    err = capsys.readouterr().err
    assert err.startswith("cylsfm odometry: error:") and str(wrong) in err, err
    bad_ckpt = tmp_path / "other.pt"
    bad_ckpt.write_bytes(b"garbage")
    assert _run(bad_ckpt, ride, "--out", tmp_path / "c") == 2
    assert str(bad_ckpt) in capsys.readouterr().err
    assert _run(ckpt, ride, "--out", tmp_path / "d", "--depth-from", tmp_path) == 2
    assert "cylsfm odometry: error:" in capsys.readouterr().err
    single = next((ride / "images").iterdir())
    assert _run(ckpt, single, "--out", tmp_path / "e") == 2
    assert "one image" in capsys.readouterr().err
    assert _run(ckpt, ride, "--out", tmp_path / "f", "--mount-yaw", "left") == 2
    assert "mount_yaw" in capsys.readouterr().err


def test_keyframe_steps_undo_the_keyframe_composition():
    rng = np.random.default_rng(0)
    steps = np.tile(np.eye(4), (7, 1, 1))
    for s in steps:
        s[:3, :3] = rotation_y(np.asarray(rng.normal(0, 0.1)))
        s[:3, 3] = rng.normal(0, 1, 3)
    every = 3
    rel = []
    for j in range(len(steps)):  # T_{K->j+1}, K = j - j % every
        t = np.eye(4)
        for i in range(j - j % every, j + 1):
            t = steps[i] @ t
        rel.append(t)
    np.testing.assert_allclose(keyframe_steps(np.stack(rel), every), steps, atol=1e-12)


def test_sigterm_stops_odometry_like_ctrl_c_and_the_run_continues(ckpt, ride, tmp_path, monkeypatch, capsys):
    """SIGTERM (a scheduler preempting the job) delivered after two chunks: the command says so and exits
    with 143, the state on disk is the two chunks', and the same command then writes the trajectory of an
    uninterrupted run."""
    import os
    import signal

    from cylsfm.data.io import read_tum

    monkeypatch.setattr(odometry_track, "CHUNK", 3)
    args = ["odometry", str(ride), "--checkpoint", str(ckpt), "--refine", "--device", "cpu", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    said = capsys.readouterr().out  # --refine comes with the bundle adjustment, and says what it kept
    assert re.search(
        r"bundle adjustment: \d+ points from \d+ features a frame, \d+ of \d+ observations kept", said
    )
    push, calls = Tracker.push, {"n": 0}

    def signalled_push(self, indices, images):
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return push(self, indices, images)

    monkeypatch.setattr(Tracker, "push", signalled_push)
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "cut")]) == 143
    assert "interrupted by SIGTERM" in capsys.readouterr().err
    assert not (tmp_path / "cut" / "trajectory.txt").exists()
    with np.load(tmp_path / "cut" / odometry_track.STATE_FILE) as saved:
        assert len(saved["stems"]) == 6 and not bool(saved["finished"])
    monkeypatch.setattr(Tracker, "push", push)
    assert main([*args, "--out", str(tmp_path / "cut")]) == 0
    whole = read_tum(tmp_path / "whole" / "trajectory.txt")
    cut = read_tum(tmp_path / "cut" / "trajectory.txt")
    np.testing.assert_allclose(cut[1], whole[1], atol=1e-6)


@pytest.fixture(scope="module")
def round_ride(tmp_path_factory) -> Path:
    """A ride once round a circle in the room (40 frames, 128x32), ending where it started."""
    angles = [2 * math.pi * i / 39 for i in range(40)]
    poses = [
        make_pose(-1.0 + 1.5 * math.cos(a), 0.1, -1.0 + 1.5 * math.sin(a), yaw_deg=-math.degrees(a))
        for a in angles
    ]
    return _room_ride(tmp_path_factory.mktemp("data") / "round", poses)


def _a_false_loop_is_not_confirmed_by_the_features(ride, ckpt, tmp_path, settings, result):
    """Frames 10 and 30, across the circle, planted as an accepted loop at the same place: the adjustment's
    features do not confirm it (no match), and the trajectory is the one without it."""
    from cylsfm.odometry import run as odometry_run
    from cylsfm.odometry.loops.loop import Loop

    real = odometry_run.find_loops

    def planted(job, state, steps):
        search = real(job, state, steps)
        return replace(search, loops=[*search.loops, Loop(10, 30, np.eye(4), 1.0, 1.0, (0.0, 0.0), 0.0)])

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(odometry_run, "find_loops", planted)
        fooled = cylsfm.odometry(ride, ckpt, tmp_path / "planted", settings)
    assert fooled.loops["accepted"] == result.loops["accepted"] + 1
    assert fooled.bundle["loops_unconfirmed"] == 1
    assert fooled.bundle["loops_confirmed"] == result.loops["accepted"]
    np.testing.assert_allclose(fooled.c2w, result.c2w, atol=1e-9)


def test_a_ride_that_comes_back_closes_its_loop(ckpt, round_ride, tmp_path):
    from cylsfm.odometry.loops import LoopSettings

    settings = OdometrySettings(
        refine=True, depth_from=round_ride.parent, progress=False, device="cpu", loops=True,
        loop=LoopSettings(min_gap=15, window=2, span=10),
    )  # fmt: skip
    out = tmp_path / "out"
    result = cylsfm.odometry(round_ride, ckpt, out, settings)
    assert result.loops is not None and result.loops["accepted"] >= 2
    accepted = [p for p in result.loops["pairs"] if p["accepted"]]
    assert all(p["j"] - p["i"] >= 15 for p in accepted)
    from cylsfm.data.io import read_tum
    from cylsfm.evaluate.motion import yaw_angle

    _, gt = read_tum(round_ride / "poses.txt")
    for p in accepted:  # every accepted loop measures the true turn between its frames
        true = math.degrees(yaw_angle(np.linalg.inv(gt[p["j"]]) @ gt[p["i"]]))
        assert abs((p["yaw_deg"] - true + 180) % 360 - 180) < 1.0
    assert any(p["i"] < 4 and p["j"] > 35 for p in accepted)  # the end seen again at the start
    closed, refined = result.metrics["loops closed"], result.metrics["refined"]
    assert closed["ape_rmse"] <= refined["ape_rmse"] * 1.01
    gap = np.linalg.norm(result.c2w[-1, :3, 3] - result.c2w[0, :3, 3])
    own = np.loadtxt(out / "trajectory_network.txt")  # (the network's: loops close the refined one)
    assert gap < 0.05 and own.shape[0] == 40
    header = (out / "trajectory.txt").read_text()
    assert "loops:" in header and "accepted" in header
    summary = __import__("json").loads((out / "odometry.json").read_text())
    assert summary["loops"]["accepted"] == result.loops["accepted"]
    # the bundle adjustment's features confirm every true loop; a planted false one is left out of it
    assert (
        result.bundle["loops_confirmed"] == result.loops["accepted"]
        and result.bundle["loops_unconfirmed"] == 0
    )
    _a_false_loop_is_not_confirmed_by_the_features(round_ride, ckpt, tmp_path, settings, result)
    # continued from the state: the loops are not looked for again, the same trajectory comes out
    again = cylsfm.odometry(round_ride, ckpt, out, settings)
    np.testing.assert_allclose(again.c2w, result.c2w)
    assert "loops" not in again.timings
    # other loop settings: the loops looked for again on the same tracking (no frame tracked again)
    strict = LoopSettings(
        min_gap=15, window=2, span=10, min_inliers=1.0, min_inliers_turned=1.0, min_inliers_support=1.0
    )
    strict = replace(settings, loop=strict)
    other = cylsfm.odometry(round_ride, ckpt, out, strict)
    assert "loops" in other.timings and "pose network" not in other.timings
    assert other.loops["accepted"] == 0 and other.loops["verified"] == result.loops["verified"]
    # without loops: no pairs, the refined trajectory
    plain = cylsfm.odometry(round_ride, ckpt, tmp_path / "plain", OdometrySettings(
        refine=True, depth_from=round_ride.parent, progress=False, device="cpu", loops=False))  # fmt: skip
    assert plain.loops is None and "loops closed" not in plain.metrics


def test_the_shared_pairs_and_depth_give_the_same_trajectory(ckpt, ride, tmp_path, monkeypatch):
    """The tracker reads each pair of frames once in the pose network's first pass (``ride_poses``) and
    hands the further passes the targets' depth it has already predicted (in the search for the direction
    of travel and in every window): the same trajectory as every window read whole, with passes that
    predict that depth again."""
    settings = OdometrySettings(save_depth_maps=True, device="cpu", progress=False, amp=False)
    fast = cylsfm.odometry(ride, ckpt, tmp_path / "fast", settings)
    given = []

    def plain(self, frames, camera, roll=0, mask=None, depth=None):
        given.append(depth is not None)
        n = frames.shape[0]
        src = torch.stack((frames[: n - 2], frames[2:]), 1)
        return self.poses(frames[1 : n - 1], src, camera, roll, mask)

    monkeypatch.setattr(odometry_track.Predictor, "ride_poses", plain)
    slow = cylsfm.odometry(ride, ckpt, tmp_path / "slow", settings)
    assert len(given) >= 2 and all(given)  # the search and the windows were handed it
    # float tolerance: the two read the frames in other batches, and on AVX2-only CPUs oneDNN's
    # convolutions then round differently (1.1e-05 m over the ride, 2026-12-06, an AMD EPYC)
    np.testing.assert_allclose(fast.c2w, slow.c2w, atol=5e-5)


@pytest.mark.parametrize("facing_deg", [0.0, 1.2])
def test_the_windows_of_the_search_for_the_direction_of_travel_are_not_computed_again(
    ckpt, tmp_path, monkeypatch, facing_deg
):
    """A camera that faces its motion (within two degrees) is not turned: the windows the search for the
    direction of travel read are the ride's first windows, kept instead of read again (the same
    trajectory as a run told to read the frames as they are, which never searches)."""
    poses = [make_pose(0.3, 0.1, -2.0 + 0.3 * i, yaw_deg=facing_deg) for i in range(N_FRAMES)]
    seq = _room_ride(tmp_path / "straight" / "ride", poses)
    read = []
    original = odometry_track.Predictor.ride_poses

    def counted(self, frames, *args, **kwargs):
        read.append(frames.shape[0] - 2)  # the windows of these frames
        return original(self, frames, *args, **kwargs)

    monkeypatch.setattr(odometry_track.Predictor, "ride_poses", counted)
    settings = OdometrySettings(refine=True, depth_from=seq.parent, device="cpu", progress=False, amp=False)
    searched = cylsfm.odometry(seq, ckpt, tmp_path / "searched", settings)
    found = json.loads((tmp_path / "searched" / "odometry.json").read_text())["direction_of_travel"]
    assert found["pairs"] > 0 and abs(found["yaw_deg"] + facing_deg) < 0.5  # the travel, seen turned
    assert found["how"].endswith("the frames not turned")
    windows = N_FRAMES - 2  # every frame but the first and the last is a window's target
    assert sum(read) == windows  # each window read once, in the search
    read.clear()
    told = cylsfm.odometry(seq, ckpt, tmp_path / "told", replace(settings, mount_yaw=0.0))
    assert sum(read) == windows
    assert (
        json.loads((tmp_path / "told" / "odometry.json").read_text())["direction_of_travel"]["how"] == "given"
    )
    np.testing.assert_allclose(searched.c2w, told.c2w, atol=1e-6)
