"""Loop closure's parts: candidates from the place descriptors, verification by direct alignment (a revisit
at another heading accepted with its yaw, planted false loops rejected: by the verification alone, and
by the odometry), the checks against the odometry,
and the pose graph (a known loop corrects an injected drift; a wrong loop among right ones is dropped)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from cylsfm.data.format import load_depth, load_image
from cylsfm.data.synth import generate_dataset
from cylsfm.errors import InputError
from cylsfm.evaluate.pose_metrics import chain_poses, trajectory_metrics
from cylsfm.geometry import invert, load_camera, place_descriptor, place_distance, roll_columns, rotation_y
from cylsfm.odometry.loops import (
    Loop,
    LoopSettings,
    Reason,
    check_loops,
    close_loops,
    loop_candidates,
    loops_from_arrays,
    loops_to_arrays,
    sequence_distances,
    verify_loops,
)


@pytest.fixture(scope="module")
def streets(tmp_path_factory):
    """Two frames of each of two towns at 128x32 with their true depth: ``(images, depths, camera)``."""
    root = tmp_path_factory.mktemp("streets")
    seqs = generate_dataset(
        root, sequences=2, frames=3, width=128, height=32, seed=4, workers=1, progress=False
    )
    images, depths = [], []
    for seq in seqs:
        for k in (0, 1):
            images.append(
                torch.from_numpy(load_image(seq / "images" / f"{k:06d}.png").copy()).permute(2, 0, 1) / 255
            )
            depths.append(torch.from_numpy(load_depth(seq / "depth" / f"{k:06d}.npy").copy())[None])
    return torch.stack(images).float(), torch.stack(depths).float(), load_camera(seqs[0] / "camera.json")


def test_a_revisit_at_another_heading_is_accepted_and_a_planted_false_loop_is_not(streets):
    images, depths, cam = streets
    shift = 40  # the camera turned: 112.5 degrees
    frames = {0: images[0], 1: roll_columns(images[0], shift, axis=-1), 2: images[2]}
    depth = {0: depths[0], 1: roll_columns(depths[0], shift, axis=-1), 2: depths[2]}
    # the odometry: frame 1 back at frame 0's place, its heading 10 degrees off; frame 2 (another town) 100 m on
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[1, :3, :3] = rotation_y(np.asarray(-math.radians(shift / 128 * 360 + 10)))
    c2w[1, 2, 3], c2w[2, 2, 3] = 0.5, 100.0
    pairs = [(0, 1, 0.1), (0, 2, 0.1)]
    revisit, false = verify_loops(pairs, frames.__getitem__, depth.__getitem__, cam, LoopSettings(), c2w=c2w)
    assert revisit.accepted and revisit.reason is Reason.ACCEPTED
    yaw = math.degrees(math.atan2(revisit.pose[0, 2], revisit.pose[2, 2]))
    assert yaw == pytest.approx(shift / 128 * 360, abs=0.5)
    assert np.linalg.norm(revisit.pose[:3, 3]) < 0.05 * float(depths[0][depths[0] > 0].median())
    assert revisit.ratio == pytest.approx(1.0, abs=0.01)
    assert false.inliers < revisit.inliers
    # another town of the same generator fits much of a rigid motion at 128x32 (the verification alone
    # may pass it); the odometry, which puts it 100 m away, rejects it
    reach = np.full(3, float(depths[0][depths[0] > 0].median()))
    checked = check_loops([revisit, false], c2w, reach, LoopSettings(support=1))
    assert checked[0].accepted
    assert not checked[1].accepted and checked[1].reason in (Reason.FEW_INLIERS, Reason.BEYOND_DRIFT)


def test_a_planted_false_loop_is_rejected_by_the_verification_alone(streets):
    """No odometry to gate it: a place that never was (the first frame's own colours and depth, its columns
    in blocks of 16 shuffled) is rejected by the compass and the direct alignment, where the same frame
    turned is accepted."""
    images, depths, cam = streets
    perm = torch.randperm(8, generator=torch.Generator().manual_seed(0))

    def scramble(x):
        return torch.cat([x[..., 16 * p : 16 * p + 16] for p in perm], -1)

    frames = {0: images[0], 1: scramble(images[0]), 2: roll_columns(images[0], 40, axis=-1)}
    depth = {0: depths[0], 1: scramble(depths[0]), 2: roll_columns(depths[0], 40, axis=-1)}
    false, revisit = verify_loops(
        [(0, 1, 0.1), (0, 2, 0.1)], frames.__getitem__, depth.__getitem__, cam, LoopSettings()
    )
    assert not false.accepted and false.reason is Reason.FEW_INLIERS
    assert revisit.accepted and false.inliers < LoopSettings().min_inliers < revisit.inliers


def test_a_revisit_a_metre_away_measures_the_step(streets):
    images, depths, cam = streets
    frames = {0: images[0], 1: roll_columns(images[1], 64, axis=-1)}  # the next frame, turned round
    depth = {0: depths[0], 1: roll_columns(depths[1], 64, axis=-1)}
    (loop,) = verify_loops([(0, 1, 0.1)], frames.__getitem__, depth.__getitem__, cam, LoopSettings())
    assert loop.accepted
    yaw = math.degrees(math.atan2(loop.pose[0, 2], loop.pose[2, 2]))
    assert abs(abs(yaw) - 180) < 3
    assert 0.3 < np.linalg.norm(loop.pose[:3, 3]) < 2.0  # metres (true depth): a step of about a metre


def test_candidates_pair_the_frames_of_a_place_seen_again():
    g = torch.Generator().manual_seed(0)
    base = torch.nn.functional.interpolate(
        torch.rand(80, 3, 4, 16, generator=g), size=(32, 128), mode="bilinear"
    )
    base[60:72] = roll_columns(base[0:12], 50, axis=-1)  # frames 60-71 revisit 0-11 at another heading
    pairs = loop_candidates(place_descriptor(base), LoopSettings(min_gap=20, window=2, per_query=1))
    assert len(pairs) >= 8, pairs
    top = pairs[:8]
    assert all(j - i == 60 for i, j, _ in top), top
    # the best pairs are the revisit's, and the revisit's frames are all among the candidates
    assert {j for i, j, _ in pairs if j - i == 60} >= set(range(62, 70))
    assert max(d for _, _, d in top) < min(d for i, j, d in pairs if j - i != 60)
    assert loop_candidates(place_descriptor(base[:15]), LoopSettings(min_gap=20)) == []


def test_sequence_distances_by_blocks_of_rows_are_the_whole_matrix_s_rows():
    desc = torch.nn.functional.normalize(
        torch.rand(40, 12, generator=torch.Generator().manual_seed(1)), dim=1
    )
    plain = place_distance(desc, desc).double().numpy()
    assert np.allclose(sequence_distances(desc, 0), plain)
    whole = sequence_distances(desc, 3)
    # by hand for one pair: the better of the same-order and the reverse-order mean over the 7 frames
    i, j = 10, 30
    same = np.mean([plain[i + t, j + t] for t in range(-3, 4)])
    back = np.mean([plain[i + t, j - t] for t in range(-3, 4)])
    assert whole[i, j] == pytest.approx(min(same, back))
    n = len(plain)

    def by_hand(q: int, c: int) -> float:  # over the frames that exist, the better of the two orders
        means = []
        for sign in (1, -1):
            ds = [
                plain[q + t, c + sign * t] for t in range(-3, 4) if 0 <= q + t < n and 0 <= c + sign * t < n
            ]
            means.append(np.mean(ds))
        return min(means)

    for q, c in ((0, 39), (1, 38), (39, 0), (38, 2), (0, 0), (20, 39)):  # at the ends: fewer frames
        assert whole[q, c] == pytest.approx(by_hand(q, c))
    for a, b in ((0, 5), (2, 9), (35, 40), (0, 40)):
        np.testing.assert_allclose(sequence_distances(desc, 3, (a, b)), whole[a:b], atol=1e-12)


def _line(n: int) -> np.ndarray:
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 2, 3] = np.arange(n, dtype=float)
    return c2w


def _loop(i: int, j: int, c2w: np.ndarray, offset: float = 0.0, turn_deg: float = 0.0) -> Loop:
    pose = invert(c2w[j]) @ c2w[i]
    pose[2, 3] += offset
    centre = -pose[:3, :3].T @ pose[:3, 3]  # camera j in frame i: kept where it is, turned
    pose[:3, :3] = rotation_y(np.asarray(math.radians(turn_deg))) @ pose[:3, :3]
    pose[:3, 3] = -pose[:3, :3] @ centre
    return Loop(i, j, pose, 1.0, 0.9, (0.0, 0.0), 0.1)


def test_checks_drop_a_loop_beyond_the_drift_and_a_loop_that_no_other_supports():
    c2w = _line(100)
    reach = np.full(100, 10.0)
    # agreeing loops 0->60, 1->61, 2->62 (the odometry's own relative poses), a lone one, and one 40 m off
    # and one at the right place but turned round (a street seen the other way round, taken for the same view)
    loops = [_loop(k, 60 + k, c2w) for k in range(3)] + [_loop(30, 90, c2w), _loop(5, 95, c2w, offset=40.0)]
    loops += [_loop(3, 63, c2w, turn_deg=180.0), _loop(4, 64, c2w, turn_deg=20.0)]
    checked = check_loops(loops, c2w, reach, LoopSettings())
    assert [lp.accepted for lp in checked] == [True, True, True, False, False, False, False]
    assert checked[3].reason is Reason.UNSUPPORTED
    assert checked[4].reason is Reason.BEYOND_DRIFT
    assert checked[5].reason is Reason.TURNED_BEYOND_DRIFT
    assert checked[6].reason is Reason.UNSUPPORTED  # 20 degrees: within the heading drift allowed
    assert checked[5].reason.message == "turned farther than the odometry's drift"
    # but not when the allowance is 10 degrees
    strict = check_loops(
        [*loops[:3], _loop(4, 64, c2w, turn_deg=20.0)], c2w, reach, LoopSettings(yaw_drift_deg=10.0)
    )
    assert strict[3].reason is Reason.TURNED_BEYOND_DRIFT
    again = loops_from_arrays(loops_to_arrays(checked))
    assert [(lp.i, lp.j, lp.reason, lp.ratio, lp.distance) for lp in again] == [
        (lp.i, lp.j, lp.reason, lp.ratio, lp.distance) for lp in checked
    ]
    np.testing.assert_allclose(again[0].pose, checked[0].pose)
    assert loops_from_arrays(loops_to_arrays([])) == []


def _weak(loop: Loop, inliers: float, reason: Reason = Reason.FEW_INLIERS) -> Loop:
    """``loop`` as the verification leaves a pair that fits less well than an accepted loop."""
    return replace(loop, inliers=inliers, reason=reason)


def test_a_loop_at_the_end_of_a_ride_is_supported_by_pairs_that_fit_less_well_but_agree():
    """A ride that ends where it started sees its start well from its last frame only: the frames before
    fit less well (seen from farther back) but their alignment found the same place."""
    c2w = _line(100)
    reach = np.full(100, 10.0)
    settings = LoopSettings()
    assert settings.support == 2
    lone = check_loops([_loop(0, 99, c2w)], c2w, reach, settings)
    assert not lone[0].accepted and lone[0].reason is Reason.UNSUPPORTED
    weak = [_weak(_loop(0, 98, c2w), 0.45), _weak(_loop(0, 97, c2w), 0.35)]
    checked = check_loops([_loop(0, 99, c2w), *weak], c2w, reach, settings)
    assert [lp.accepted for lp in checked] == [True, False, False]  # the weak pairs support, never join
    assert [lp.reason for lp in checked[1:]] == [Reason.FEW_INLIERS, Reason.FEW_INLIERS]
    # not supported: a pair below the support's inliers; one whose pose disagrees (8 m off); one turned
    # round; one that asks for more than the odometry's drift
    for other in (
        _weak(_loop(0, 98, c2w), settings.min_inliers_support - 0.01),
        _weak(_loop(0, 98, c2w, offset=8.0), 0.45),
        _weak(_loop(0, 98, c2w, turn_deg=180.0), 0.45),
        _weak(_loop(0, 98, c2w, offset=40.0), 0.45),
    ):
        alone = check_loops([_loop(0, 99, c2w), other], c2w, reach, settings)
        assert not alone[0].accepted, other
    # a pair the two directions disagreed on supports nothing either
    bad = _weak(_loop(0, 98, c2w), 0.45, Reason.DISAGREE)
    assert not check_loops([_loop(0, 99, c2w), bad], c2w, reach, settings)[0].accepted
    # a street driven back the other way: a loop turned round is supported by accepted loops only
    back = _line(100)
    back[50:, :3, :3] = rotation_y(np.asarray(math.pi))
    back[50:, 2, 3] = 99.0 - np.arange(50, 100)
    weak_turned = check_loops([_loop(10, 89, back), _weak(_loop(11, 88, back), 0.45)], back, reach, settings)
    assert not weak_turned[0].accepted
    both = check_loops([_loop(10, 89, back), _loop(11, 88, back)], back, reach, settings)
    assert both[0].accepted and both[1].accepted


def _circle(n: int = 100, radius: float = 16.0) -> np.ndarray:
    gt = np.tile(np.eye(4), (n, 1, 1))
    for k, a in enumerate(np.linspace(0, 2 * np.pi, n + 1)[:-1]):
        gt[k, :3, :3] = rotation_y(np.asarray(a, dtype=np.float64))
        gt[k, 0, 3], gt[k, 2, 3] = radius * (1 - np.cos(a)), radius * np.sin(a)
    return gt


def _drifted(gt: np.ndarray) -> np.ndarray:
    """The true steps with a growing scale (+0.1% a step) and a rotation bias (0.11 degrees a step)."""
    steps = np.stack([invert(gt[j + 1]) @ gt[j] for j in range(len(gt) - 1)])
    for j in range(len(steps)):
        steps[j, :3, 3] *= 1 + 0.001 * j
        steps[j, :3, :3] = rotation_y(np.asarray(0.002)) @ steps[j, :3, :3]
    return steps


def _ape(gt: np.ndarray, c2w: np.ndarray) -> float:
    t = np.arange(len(gt)) * 0.2
    return trajectory_metrics(gt, t, c2w, t)[0]["ape_rmse"]


def test_the_pose_graph_with_a_known_loop_corrects_an_injected_drift():
    gt = _circle()
    steps = _drifted(gt)
    n = len(gt)
    ratio = 1 + 0.001 * (n - 2)  # the odometry's unit at the end against the start's
    loop = Loop(0, n - 1, invert(gt[n - 1]) @ gt[0], ratio, 0.9, (0.0, 0.0), 0.1)
    before = chain_poses(steps)
    after, scales = close_loops(steps, [loop])
    assert _ape(gt, after) < 0.2 * _ape(gt, before)
    assert np.linalg.norm(after[-1, :3, 3] - after[0, :3, 3]) < 0.02 * 2 * np.pi * 16
    # the scale's drift is found: the last frame's unit is 1/ratio (0.91) of the first's; the graph, which
    # also trusts the steps' scale, goes more than half way there (0.95), not 1
    assert scales[0] == pytest.approx(1.0) and 1 / ratio - 0.01 < scales[-1] < 0.97
    # the loop's ratio is what corrects it: the same loop claiming no change of scale leaves it at 1, and
    # the ride further from the truth
    unscaled, kept = close_loops(steps, [replace(loop, ratio=1.0)])
    assert kept[-1] == pytest.approx(1.0, abs=0.01)
    assert _ape(gt, after) < 0.7 * _ape(gt, unscaled)
    # no accepted loop: the steps chained
    same, ones = close_loops(steps, [replace(loop, reason=Reason.UNSUPPORTED)])
    np.testing.assert_allclose(same, before)
    assert np.all(ones == 1)


def test_a_wrong_loop_among_right_ones_is_dropped():
    gt = _circle()
    steps = _drifted(gt)
    n = len(gt)
    ratio = 1 + 0.001 * (n - 2)
    right = [Loop(k, n - 1 - k, invert(gt[n - 1 - k]) @ gt[k], ratio, 0.9, (0, 0), 0.1) for k in range(3)]
    wrong_pose = invert(gt[70]) @ gt[20]
    wrong_pose[:3, 3] = 0.0  # claims frames 20 and 70 (on opposite sides of the circle) are one place
    wrong = Loop(20, 70, wrong_pose, 1.0, 0.9, (0, 0), 0.1)
    good, _ = close_loops(steps, right)
    with_wrong, _ = close_loops(steps, [*right, wrong])
    # the right loops close the ride (a graph that ignored every loop would not)...
    assert _ape(gt, good) < 0.2 * _ape(gt, chain_poses(steps))
    # ...and the wrong one changes nothing: frames 20 and 70 stay on opposite sides of the circle
    assert _ape(gt, with_wrong) == pytest.approx(_ape(gt, good), rel=0.02)
    assert np.linalg.norm(with_wrong[70, :3, 3] - with_wrong[20, :3, 3]) > 20.0


def test_the_heading_allowed_grows_with_the_frames_between_but_stays_short_of_a_quarter_turn():
    """The odometry's heading may have drifted more the longer the way between two frames, but never so
    far that a street seen the other way round (or a crossing a quarter turn round) could pass."""
    settings = LoopSettings()
    assert math.degrees(settings.yaw_allowance(0, 100)) == pytest.approx(40.0)
    assert math.degrees(settings.yaw_allowance(300, 0)) == pytest.approx(60.0)
    assert math.degrees(settings.yaw_allowance(0, 5000)) == pytest.approx(80.0)
    c2w = _line(600)
    reach = np.full(600, 10.0)
    # a loop turned 70 degrees from the odometry 500 frames on is within the drift; 85 degrees is not
    loops = [
        _loop(0, 500, c2w, turn_deg=70.0),
        _loop(1, 501, c2w, turn_deg=70.0),
        _loop(2, 502, c2w, turn_deg=85.0),
    ]
    checked = check_loops(loops, c2w, reach, settings)
    assert [lp.accepted for lp in checked] == [True, True, False]
    assert checked[2].reason is Reason.TURNED_BEYOND_DRIFT
    with pytest.raises(InputError, match="yaw_drift_max_deg"):
        LoopSettings(yaw_drift_max_deg=200.0)
