"""The visual compass and the diagnostics that tell a measured ego-motion from a prior, each on a case with a
known answer; a pose network with a slot prior is flagged, an oracle is not."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cylsfm.data import scan_dataset
from cylsfm.evaluate.motion import (
    MotionRecord,
    format_motion_table,
    forward_backward,
    motion_verdict,
    rotation_error_deg,
    standing_ratio,
    steps_of,
    swap_cosine,
    turn_response,
    yaw_angle,
)
from cylsfm.evaluate.pose import evaluate_pose
from cylsfm.geometry import (
    column_shift,
    compass_yaw,
    roll_angle,
    roll_columns,
    roll_pose,
    rotation_x,
    yaw_transform,
)


def _panorama(seed: int = 0, width: int = 256, height: int = 48) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(2, 3, height, width, generator=g)
    return torch.nn.functional.avg_pool2d(x, 3, 1, 1)  # some smoothness, as in real images


def _fourier_shift(x: torch.Tensor, s: float) -> torch.Tensor:
    w = x.shape[-1]
    k = torch.arange(w // 2 + 1, dtype=torch.float64)
    spectrum = torch.fft.rfft(x.double(), dim=-1) * torch.exp(-2j * math.pi * k * s / w)
    return torch.fft.irfft(spectrum, n=w, dim=-1)


# --------------------------------------------------------------------------------------- the compass
@pytest.mark.parametrize("k", [0, 1, -1, 5, -37, 100, 127, -128])
def test_compass_is_exact_on_rolled_panoramas(k):
    a = _panorama()
    assert column_shift(a, roll_columns(a, k)).tolist() == pytest.approx([k, k], abs=1e-9)


@pytest.mark.parametrize("s", [0.3, -0.3, 12.75, -64.4, 127.6])
def test_compass_is_sub_pixel_on_fractional_rolls(s):
    a = _panorama(1)
    got = column_shift(a, _fourier_shift(a, s))
    wrapped = (s + 128) % 256 - 128
    assert got.tolist() == pytest.approx([wrapped, wrapped], abs=1e-4)


def test_compass_yaw_is_the_rotation_of_the_relative_pose():
    """The yaw read from a rolled panorama is the rotation the geometry gives the roll (roll_pose)."""
    a = _panorama(2)
    for k in (17, -40):
        yaw = float(compass_yaw(a, roll_columns(a, k))[0])
        assert yaw == pytest.approx(roll_angle(k, 256), abs=1e-9)
        # a camera that turned by the roll: p_b = Y p_a, with Y = roll_pose(identity) of the roll
        expected = roll_pose(np.eye(4), k, 256)
        assert yaw_angle(expected) == pytest.approx(0.0, abs=1e-12)  # conjugation keeps the identity
        assert yaw_angle(yaw_transform(roll_angle(k, 256), np.eye(4))) == pytest.approx(yaw, abs=1e-9)


def test_compass_near_a_prior_picks_the_peak_of_a_street_seen_the_other_way_round():
    """A scene that repeats every half turn (a straight street looks much the same ahead and behind) has
    two equal peaks; a prior within a quarter turn picks the one near it."""
    half = _panorama(3)[..., :128]
    a = torch.cat((half, half), -1)
    b = roll_columns(a, 20)
    for got in column_shift(a, b).tolist():  # without a prior either peak (which one is rounding's choice)
        assert got == pytest.approx(20, abs=1e-6) or got == pytest.approx(-108, abs=1e-6)
    near = torch.tensor([-100.0, 150.0])  # both nearest to 148 (= 20 + 128, i.e. -108)
    assert column_shift(a, b, near=near, within=40.0).tolist() == pytest.approx([-108, -108], abs=1e-6)
    yaw = compass_yaw(a, b, near=torch.tensor([3.0, 3.0]), within=math.radians(40))
    assert yaw.tolist() == pytest.approx([roll_angle(-108, 256)] * 2, abs=1e-9)
    # a window too narrow for any true peak still returns the best shift inside it
    inside = column_shift(a, b, near=torch.tensor([60.0, 60.0]), within=torch.tensor([5.0, 5.0]))
    assert ((inside >= 54) & (inside <= 66)).all()  # the window's peak, refined by at most a column
    with pytest.raises(ValueError, match="within"):
        column_shift(a, b, near=near)


def test_compass_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="shape"):
        column_shift(torch.zeros(1, 3, 8, 32), torch.zeros(1, 3, 8, 16))


# --------------------------------------------------------------------------------------- the measures
def _yaw_steps(degrees) -> np.ndarray:
    return np.stack([yaw_transform(math.radians(d), np.eye(4)) for d in degrees])


def test_rotation_error_and_yaw_of_known_rotations():
    a = _yaw_steps([10.0, -3.0])
    b = _yaw_steps([4.0, -3.0])
    assert rotation_error_deg(a, b) == pytest.approx([6.0, 0.0], abs=1e-9)
    assert np.degrees(yaw_angle(a)) == pytest.approx([10.0, -3.0])
    pitch = np.eye(4)
    pitch[:3, :3] = rotation_x(np.asarray(math.radians(7.0)))
    assert rotation_error_deg(pitch[None], np.eye(4)[None]) == pytest.approx([7.0])


def test_turn_response_on_known_cases():
    true = _yaw_steps([-8, -4, -3, 0, 0.5, 3, 5, 9])
    exact = turn_response(true, true)
    assert exact["n_turning"] == 6 and exact["n_steps"] == 8
    assert exact["yaw_slope"] == pytest.approx(1.0) and exact["yaw_correlation"] == pytest.approx(1.0)
    assert exact["rot_err_deg"] == pytest.approx(0.0, abs=1e-6)
    never = turn_response(_yaw_steps([0] * 8), true)
    assert never["yaw_slope"] == 0.0 and never["yaw_correlation"] == 0.0
    assert never["rot_err_deg_turning"] == pytest.approx(np.mean([8, 4, 3, 3, 5, 9]))
    too_few = turn_response(_yaw_steps([0, 3, 0]), _yaw_steps([0, 3, 0]))
    assert too_few["yaw_slope"] is None and too_few["n_turning"] == 1


def _translation(vectors) -> np.ndarray:
    out = np.tile(np.eye(4), (len(vectors), 1, 1))
    out[:, :3, 3] = vectors
    return out


def test_standing_swap_and_forward_backward_on_known_cases():
    real = _translation([[0, 0, 1.0], [0, 0, 1.2], [0, 0, 0.8]])
    assert standing_ratio(_translation([[0, 0, 0.5]] * 3), real) == pytest.approx(0.5)
    pairs = np.stack([_translation([[0, 0, -1.0], [0, 0, 1.0]])] * 4)  # [N, S=2, 4, 4]
    assert swap_cosine(pairs, pairs) == pytest.approx(1.0)
    assert swap_cosine(pairs, pairs[:, ::-1]) == pytest.approx(-1.0)  # a slot prior
    ab = _translation([[0, 0, 1.0]] * 3)
    consistent = forward_backward(ab, np.linalg.inv(ab), usual_step=1.0)
    assert consistent["fb_trans_ratio"] == pytest.approx(0) and consistent["fb_rot_deg"] == pytest.approx(0)
    same_way = forward_backward(ab, ab, usual_step=1.0)  # "forward" both ways: two steps off
    assert same_way["fb_trans_ratio"] == pytest.approx(2.0)
    turned = forward_backward(_yaw_steps([2.0]), _yaw_steps([2.0]), usual_step=1.0)
    assert turned["fb_rot_deg"] == pytest.approx(4.0)


def test_verdict_names_each_failed_check():
    good = {"yaw_slope": 1.0, "yaw_correlation": 0.95, "standing_ratio": 0.1, "swap_cosine": 0.9}
    assert motion_verdict(good) == (True, [])
    measured, failures = motion_verdict({**good, "standing_ratio": 0.89, "swap_cosine": -1.0})
    assert measured is False and len(failures) == 2
    assert "standing_ratio" in failures[0] and "swap_cosine" in failures[1]
    assert motion_verdict({"yaw_slope": None}) == (None, [])


def test_steps_of_inverts_chaining():
    from cylsfm.evaluate.pose import chain_poses

    steps = _yaw_steps([1, -2, 3])
    steps[:, :3, 3] = [[0, 0, 1], [0.1, 0, 1], [0, 0, 0.5]]
    assert np.allclose(steps_of(chain_poses(steps)), steps)


# --------------------------------------------------------------------------------------- evaluations
class _SlotPrior:
    """A pose network that ignores its input: the frame before the target is one step back, the frame
    after it one step forward, never a turn (what the paper's head learned on forward-only rides)."""

    window_length, frame_stride = 3, 1

    def poses(self, target, sources, camera):
        out = np.tile(np.eye(4), (target.shape[0], 2, 1, 1))
        out[:, 0, 2, 3], out[:, 1, 2, 3] = 1.0, -1.0  # p_src = p_tgt -+ step along z
        return torch.from_numpy(out)


class _Oracle:
    """A pose network that returns the true relative poses of the frames it is shown (found by their
    pixels), whatever their order: what a network that measures the motion would do."""

    window_length, frame_stride = _SlotPrior.window_length, _SlotPrior.frame_stride

    def __init__(self, seq):
        from cylsfm.evaluate.frames import load_images

        frames = load_images(seq.images)
        self.index = {self._key(f): i for i, f in enumerate(frames)}
        self.c2w = seq.poses

    @staticmethod
    def _key(image):
        return (image * 255).round().to(torch.uint8).numpy().tobytes()

    def poses(self, target, sources, camera):
        out = np.empty((target.shape[0], sources.shape[1], 4, 4))
        for b in range(target.shape[0]):
            t = self.index[self._key(target[b])]
            for s in range(sources.shape[1]):
                j = self.index[self._key(sources[b, s])]
                out[b, s] = np.linalg.inv(self.c2w[j]) @ self.c2w[t]
        return torch.from_numpy(out)


def test_a_slot_prior_is_flagged_and_an_oracle_is_not(synth_with_turns):
    root, seq = synth_with_turns
    prior = evaluate_pose(_SlotPrior(), root, split=None)
    m = prior["motion"]["model"]
    assert m["standing_ratio"] == pytest.approx(1.0) and m["swap_cosine"] == pytest.approx(-1.0)
    assert prior["motion"]["verdict"]["measured"] is False
    assert "NOT MEASURED" in format_motion_table(prior["motion"])
    oracle = evaluate_pose(_Oracle(seq), root, split=None)
    o = oracle["motion"]["model"]
    assert o["standing_ratio"] == pytest.approx(0.0, abs=1e-9) and o["swap_cosine"] == pytest.approx(1.0)
    assert o["fb_trans_ratio"] == pytest.approx(0.0, abs=1e-9) and o["fb_rot_deg"] == pytest.approx(
        0.0, abs=1e-5
    )
    assert o["rot_err_deg"] == pytest.approx(0.0, abs=1e-5)
    assert oracle["motion"]["verdict"]["measured"] is True
    # the compass is reported beside it and turns with the ride
    compass = oracle["motion"]["compass"]
    still = oracle["motion"]["constant_velocity"]
    assert compass["rot_err_deg_turning"] < 0.5 * still["rot_err_deg_turning"]
    assert oracle["compass"]["ate_mean"] > 0 and oracle["motion"]["n_turning"] >= 5


def test_compass_turns_with_a_synthetic_ride(synth_with_turns):
    """On a rendered ride (parallax, occlusions, not a pure roll) the compass follows the true yaw."""
    from cylsfm.evaluate.pose_source import compass_steps

    _, seq = synth_with_turns
    true = steps_of(seq.poses)
    response = turn_response(compass_steps(seq.images), true)
    assert response["n_turning"] >= 5
    assert 0.75 <= response["yaw_slope"] <= 1.15 and response["yaw_correlation"] >= 0.9
    assert response["rot_err_deg"] < 1.5  # the compass sees the yaw, not the pitch and roll wobble


def test_motion_record_without_probes_reports_turns_only():
    record = MotionRecord()
    true = _yaw_steps([0, 3, 4, -5, 6, -7, 0])
    record.add(true, true)
    summary = record.summary()
    assert summary["n_turning"] == 5 and summary["compass"] is None
    assert "standing_ratio" not in summary["model"] and summary["verdict"]["measured"] is True


@pytest.fixture(scope="module")
def synth_with_turns(tmp_path_factory):
    """One synthetic ride of 40 frames at 256x64 through short blocks, which turns at a corner (13 steps
    turn by more than 2 degrees), as a dataset root and its sequence."""
    from cylsfm.data.synth import generate_dataset
    from cylsfm.data.synth.config import SynthConfig

    root = tmp_path_factory.mktemp("turns") / "data"
    town = SynthConfig(block_size=(20.0, 30.0), stop_probability=0.0)
    generate_dataset(root, 1, 40, 256, 64, seed=3, workers=1, config=town, progress=False)
    seq = scan_dataset(root)[0]
    return root, seq
