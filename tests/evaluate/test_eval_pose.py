"""Pose evaluation: snippet ATE, chaining network windows, evo APE/RPE, baselines, the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from cylsfm.cli import main
from cylsfm.data import make_splits, read_tum, scan_dataset, write_tum
from cylsfm.errors import InputError
from cylsfm.evaluate.pose import (
    ate_positions,
    chain_poses,
    consecutive_from_windows,
    constant_velocity_trajectory,
    evaluate_pose,
    relative_positions,
    snippet_ate,
    snippet_ates,
    trajectory_metrics,
)
from cylsfm.evaluate.pose_metrics import baseline_trajectories
from cylsfm.geometry import axis_angle_to_matrix, relative_pose, yaw_matrix


def _trajectory(n: int, seed: int = 0) -> np.ndarray:
    """A curved camera-to-world trajectory ``[n,4,4]`` with rotations about every axis."""
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    rot = np.eye(3)
    pos = np.array([3.0, -1.5, 7.0])
    for i in range(n):
        out[i, :3, :3], out[i, :3, 3] = rot, pos
        w = torch.tensor(rng.normal(0, 0.08, 3) + np.array([0.0, 0.1, 0.0]))
        rot = rot @ axis_angle_to_matrix(w).numpy()
        pos = pos + rot @ np.array([0.1, 0.02, 1.0]) * rng.uniform(0.5, 1.5)
    return out


def _sim3(c2w: np.ndarray, scale: float, seed: int = 1) -> np.ndarray:
    """``c2w`` moved by a similarity: positions ``s R p + t``, orientations ``R R_i``."""
    rng = np.random.default_rng(seed)
    r = axis_angle_to_matrix(torch.tensor(rng.normal(0, 1, 3))).numpy()
    t = rng.normal(0, 10, 3)
    out = c2w.copy()
    out[:, :3, :3] = r @ c2w[:, :3, :3]
    out[:, :3, 3] = scale * c2w[:, :3, 3] @ r.T + t
    return out


# --------------------------------------------------------------------------------------- snippet ATE
def test_ate_by_hand():
    gt = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2]], dtype=float)
    pred = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 1]], dtype=float)
    # s = (1 + 2) / (1 + 1) = 1.5; residuals 0, -0.5, 0.5; sqrt(0.5) / 3 (root of the sum, divided by N)
    assert ate_positions(gt, pred) == pytest.approx(math.sqrt(0.5) / 3)
    # zero motion: s = 0, the error is the ground truth itself
    assert ate_positions(gt, np.zeros((3, 3))) == pytest.approx(math.sqrt(5) / 3)
    with pytest.raises(InputError):
        ate_positions(gt, pred[:2])


def test_snippet_ate_perfect_scaled_and_perturbed():
    gt = _trajectory(5)
    assert snippet_ate(gt, gt) == pytest.approx(0, abs=1e-12)
    # another world frame and another scale: relative to the first frame and scale-fitted -> 0
    assert snippet_ate(gt, _sim3(gt, 0.37)) == pytest.approx(0, abs=1e-9)
    noisy = gt.copy()
    noisy[3, :3, 3] += [0.3, 0.0, -0.2]
    assert snippet_ate(gt, noisy) > 0.01
    assert relative_positions(gt)[0] == pytest.approx(np.zeros(3))


def test_snippet_baselines():
    # a camera driving straight along its +z at constant speed: constant velocity is perfect
    straight = _sim3(constant_velocity_trajectory(9, 1.3), 1.0)
    a = snippet_ates(straight, straight, snippet=5)
    assert len(a["model"]) == 5
    assert np.allclose(a["constant_velocity"], 0, atol=1e-9) and np.allclose(a["model"], 0, atol=1e-9)
    # zero motion: sqrt(sum of squared distances from the first frame) / N
    want = math.sqrt(sum((1.3 * i) ** 2 for i in range(5))) / 5
    assert np.allclose(a["zero_motion"], want)
    # a turning camera: constant velocity is no longer perfect
    b = snippet_ates(_trajectory(9), None, snippet=5)
    assert "model" not in b and np.all(b["constant_velocity"] > 1e-3)
    # snippets with an unmatched frame are skipped
    matched = np.ones(9, dtype=bool)
    matched[4] = False
    assert len(snippet_ates(straight, straight, 5, matched)["model"]) == 0
    matched[4], matched[0] = True, False
    assert len(snippet_ates(straight, straight, 5, matched)["zero_motion"]) == 4


# --------------------------------------------------------------------------------------- chaining
def _steps(c2w: np.ndarray) -> np.ndarray:
    t = torch.from_numpy(c2w)
    return relative_pose(t[:-1], t[1:]).numpy()  # T_{j->j+1}


def test_chaining_reproduces_trajectory():
    c2w = _trajectory(12)
    chained = chain_poses(_steps(c2w))
    want = np.linalg.inv(c2w[0]) @ c2w
    assert np.allclose(chained, want, atol=1e-9)
    assert np.allclose(chained[0], np.eye(4))


@pytest.mark.parametrize("seq_length", [3, 5])
def test_consecutive_poses_from_network_windows(seq_length):
    c2w = torch.from_numpy(_trajectory(9, seed=2))
    k = (seq_length - 1) // 2
    m = len(c2w)
    windows = {}
    for c in range(k, m - k):
        src = [f for f in range(c - k, c + k + 1) if f != c]
        windows[c] = relative_pose(c2w[c].expand(len(src), 4, 4), c2w[src]).numpy()  # what a perfect net says
    steps = consecutive_from_windows(windows, m, seq_length)
    assert np.allclose(steps, _steps(c2w.numpy()), atol=1e-9)
    assert np.allclose(chain_poses(steps), np.linalg.inv(c2w[0].numpy()) @ c2w.numpy(), atol=1e-9)
    # the middle steps come from the window centred on their first frame: corrupt another window's
    # prediction for that pair and the step must not change
    broken = {c: w.copy() for c, w in windows.items()}
    broken[k + 1][k - 1] = np.eye(4)  # the window centred on k+1: its prediction for source k
    again = consecutive_from_windows(broken, m, seq_length)
    assert np.allclose(again[k], steps[k], atol=1e-9)
    with pytest.raises(InputError):
        consecutive_from_windows(windows, seq_length - 1, seq_length)


# --------------------------------------------------------------------------------------- evo
def test_evo_ape_of_sim3_copy_is_zero():
    gt = _trajectory(20)
    times = np.arange(20) * 0.1
    est = _sim3(gt, 0.05)
    m, aligned = trajectory_metrics(gt, times, est, times)
    assert m["ape_rmse"] < 1e-6 and m["rpe_trans_rmse"] < 1e-6 and m["rpe_rot_deg_rmse"] < 1e-4
    assert m["scale"] == pytest.approx(20.0) and m["n_frames"] == 20
    assert np.allclose(aligned, gt[:, :3, 3], atol=1e-6)
    noisy = est.copy()
    noisy[5:, :3, 3] += 0.02
    m2, _ = trajectory_metrics(gt, times, noisy, times)
    assert m2["ape_rmse"] > 0.01


def test_baseline_trajectories():
    line = _sim3(constant_velocity_trajectory(10, 0.8), 1.0)
    times = np.arange(10.0)
    base, curves = baseline_trajectories(line, times, np.arange(10))
    assert base["constant_velocity"]["ape_rmse"] < 1e-9
    assert base["constant_velocity"]["scale"] == pytest.approx(0.8)
    # zero motion at the centroid: the RMS distance of the positions from their centroid
    pos = line[:, :3, 3]
    want = math.sqrt(np.mean(np.sum((pos - pos.mean(0)) ** 2, 1)))
    assert base["zero_motion"]["ape_rmse"] == pytest.approx(want)
    assert np.allclose(curves["constant velocity"], pos, atol=1e-9)


# --------------------------------------------------------------------------------------- datasets / CLI
@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """2 synthetic sequences x 8 frames at 128x32 (one for training, one for testing) and an untrained
    checkpoint."""
    from cylsfm.data.synth import generate_dataset
    from helpers import untrained_checkpoint

    base = tmp_path_factory.mktemp("evalpose")
    root = base / "data"
    generate_dataset(root, sequences=2, frames=8, width=128, height=32, seed=4, workers=1, progress=False)
    make_splits(root, mode="sequence", fractions=(0.5, 0.0, 0.5))
    ckpt = untrained_checkpoint(base)
    return root, ckpt


def test_ground_truth_as_trajectory_scores_zero(synth, tmp_path):
    root, _ = synth
    traj = tmp_path / "gt"
    for seq in scan_dataset(root):
        t, c2w = read_tum(seq.path / "poses.txt")
        write_tum(traj / f"{seq.name}.txt", t, _sim3(c2w, 3.0))  # another frame and scale
    r = evaluate_pose(str(traj), root, split=None, snippet=5)
    assert r["n_snippets"] == 2 * 4
    assert r["model"]["ate_mean"] == pytest.approx(0, abs=1e-9)
    assert r["model"]["ape_rmse"] < 1e-6
    assert r["zero_motion"]["ate_mean"] > 0.1 and r["constant_velocity"]["ate_mean"] > 0


def test_cli_pose_checkpoint_then_trajectory(synth, tmp_path, capsys):
    root, ckpt = synth
    test_seq = (root / "splits" / "default" / "test.txt").read_text().split("\n")[2].split()[0]
    out, js = tmp_path / "traj", tmp_path / "pose.json"
    args = ["evaluate", "pose", "--data", str(root), "--no-progress", "--json", str(js)]
    assert main([*args, "--checkpoint", str(ckpt), "--device", "cpu", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "constant velocity" in text and "model/zero motion" in text
    data = json.loads(js.read_text())
    assert {"ate_mean", "ate_std", "n_snippets", "ape_rmse", "baselines", "sequences", "meta"} <= set(data)
    assert set(data["baselines"]) == {"zero_motion", "constant_velocity", "compass"}
    assert "is the motion measured?" in text and "verdict:" in text and "compass" in text
    assert data["motion"]["model"]["standing_ratio"] is not None and "verdict" in data["motion"]
    for b in data["baselines"].values():
        assert {"ate_mean", "ate_std", "ape_rmse"} <= set(b) and b["ate_mean"] > 0
    # only the test sequence, whole: 8 frames, 4 snippets of 5
    assert list(data["sequences"]) == [test_seq]
    assert data["n_snippets"] == 4 and data["ate_mean"] > 0 and data["ate_std"] >= 0
    assert sorted(p.name for p in out.iterdir()) == [f"{test_seq}.png", f"{test_seq}.txt"]
    seq = next(s for s in scan_dataset(root) if s.name == test_seq)
    t, c2w = read_tum(out / f"{test_seq}.txt")
    assert np.allclose(t, seq.timestamps) and np.allclose(c2w[0], np.eye(4), atol=1e-9)
    assert (out / f"{test_seq}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the written trajectory, scored as another method's (directory or single file): the same numbers
    for given in (out, out / f"{test_seq}.txt"):
        js2 = tmp_path / "again.json"
        assert main([*args[:-1], str(js2), "--trajectory", str(given)]) == 0
        again = json.loads(js2.read_text())
        assert again["ate_mean"] == pytest.approx(data["ate_mean"], rel=1e-6)
        for name, b in data["baselines"].items():
            assert again["baselines"][name]["ate_mean"] == pytest.approx(b["ate_mean"])
    # a missing trajectory file: exit 2, the file named
    (out / f"{test_seq}.txt").unlink()
    capsys.readouterr()
    assert main([*args, "--trajectory", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(out / f"{test_seq}.txt") in err and "Traceback" not in err


class _OraclePoses:
    """A stand-in for the pose network that returns the true relative poses of the frames it is shown.

    It finds out how far its frames were rolled (by matching them with the dataset's own frames) and turns
    the true motion with the roll ``turn`` times: ``1`` is what an equivariant network must do (a panorama
    rolled by ``k`` of ``W`` columns is the camera turned by ``yaw_matrix(2 pi k / W)``, so ``T`` becomes
    ``Y T Y^-1``), ``0`` ignores the roll as the paper's roll-invariant pose head must, ``-1`` turns the
    wrong way. Built from the public geometry only (``yaw_matrix``), not from the evaluator's helpers.
    """

    def __init__(self, seq, turn: int):
        from cylsfm.data import load_image

        self.frames = [
            torch.from_numpy(np.array(load_image(p))).permute(2, 0, 1).float() / 255 for p in seq.images
        ]
        self.c2w = seq.poses
        self.turn = turn
        self.window_length, self.frame_stride = 3, 1

    def _locate(self, image):
        w = image.shape[-1]
        for i, f in enumerate(self.frames):
            for k in range(w):
                if torch.allclose(torch.roll(f, k, -1), image, atol=1e-6):
                    return i, k
        raise AssertionError("frame not found")

    def poses(self, target, sources, camera):
        out = []
        for b in range(target.shape[0]):
            t, k = self._locate(target[b])
            yaw = np.eye(4)
            yaw[:3, :3] = yaw_matrix(self.turn * 2 * math.pi * k / camera.width, torch.float64).numpy()
            rel = []
            for s in range(sources.shape[1]):
                j, _ = self._locate(sources[b, s])
                rel.append(yaw @ np.linalg.inv(self.c2w[j]) @ self.c2w[t] @ np.linalg.inv(yaw))
            out.append(np.stack(rel))
        return torch.from_numpy(np.stack(out))


def test_yaw_rolled_evaluation_turns_the_ground_truth_with_the_images(synth):
    """An equivariant oracle scores zero on yaw-rolled sequences; a roll-invariant one does not."""
    root, _ = synth
    seq = scan_dataset(root)[1]
    kwargs = {"split": "test", "snippet": 5, "yaw_roll": 3}
    exact = evaluate_pose(_OraclePoses(seq, turn=1), root, **kwargs)
    assert exact["model"]["ate_mean"] == pytest.approx(0, abs=1e-6)
    assert exact["model"]["ape_rmse"] == pytest.approx(0, abs=1e-6)
    assert exact["model"]["rpe_trans_rmse"] == pytest.approx(0, abs=1e-6)
    roll = exact["sequences"][seq.name]["yaw_roll_columns"]
    assert 0 < roll < seq.camera.width and 2 * roll != seq.camera.width  # a turn whose sign matters
    blind = evaluate_pose(_OraclePoses(seq, turn=0), root, **kwargs)
    assert blind["model"]["ate_mean"] > 0.05
    plain = evaluate_pose(_OraclePoses(seq, turn=0), root, split="test", snippet=5)
    assert plain["model"]["ate_mean"] == pytest.approx(0, abs=1e-6)


def test_yaw_rolled_evaluation_refuses_the_turn_the_wrong_way(synth):
    """An oracle that turns the motion with the roll the wrong way (off by twice the roll) scores badly:
    the evaluation knows which way a rolled panorama turned."""
    root, _ = synth
    seq = scan_dataset(root)[1]
    kwargs = {"split": "test", "snippet": 5, "yaw_roll": 3}
    wrong = evaluate_pose(_OraclePoses(seq, turn=-1), root, **kwargs)
    assert wrong["model"]["ate_mean"] > 0.05 and wrong["model"]["rpe_trans_rmse"] > 0.5
    # its chained trajectory is the true one turned as a whole, which the Sim(3) alignment of the APE
    # removes: the snippet ATE and the RPE are the measures that see a wrong turn
    assert wrong["model"]["ape_rmse"] == pytest.approx(0, abs=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"snippet": 1}, "snippet"),
        ({"stride": 0}, "stride"),
        ({"batch_size": 0}, "batch_size"),
    ],
)
def test_invalid_arguments_are_input_errors_before_any_file_is_read(tmp_path, kwargs, match):
    # checked first: the (empty) dataset would otherwise be the error
    for given in (str(tmp_path), _OraclePoses.__new__(_OraclePoses)):
        with pytest.raises(InputError, match=match):
            evaluate_pose(given, tmp_path / "nothing", **kwargs)
    with pytest.raises(InputError, match="yaw_roll"):
        evaluate_pose(str(tmp_path), tmp_path / "nothing", yaw_roll=0)


def test_a_thousand_float32_steps_chain_to_rotations():
    """Steps whose rotations are rotations only to float32's precision (as the networks give them) chain
    into poses that are still rotations after 2000 frames, which evo's metrics require."""
    from cylsfm.evaluate.pose_metrics import chain_poses, trajectory_metrics
    from cylsfm.geometry import rotation_y

    rng = np.random.default_rng(0)
    steps = np.tile(np.eye(4), (2000, 1, 1))
    steps[:, :3, :3] = rotation_y(np.asarray(rng.normal(0, 0.05, 2000)))
    steps[:, 2, 3] = -1.0
    noisy = steps.astype(np.float32) + rng.normal(0, 3e-7, steps.shape).astype(np.float32)
    c2w = chain_poses(noisy)
    gram = np.einsum("nji,njk->nik", c2w[:, :3, :3], c2w[:, :3, :3])
    assert np.abs(gram - np.eye(3)).max() < 1e-9
    times = np.arange(2001) * 0.2
    stats, _ = trajectory_metrics(chain_poses(steps), times, c2w, times)
    assert stats["ape_rmse"] < 1.0
