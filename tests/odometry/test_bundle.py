"""The bundle adjustment on bearings: keypoints to bearings against the closed forms, a ride recovered from
exact correspondences and perturbed poses, a planted wrong match rejected, and a stretch without
features held by the odometry's steps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cylsfm.geometry import CylindricalCamera, EquirectangularCamera, invert, rotation_y
from cylsfm.geometry.bearings import bearing_pixels, pixel_bearings
from cylsfm.odometry.bundle import BundleSettings, Observations, bundle_adjust, triangulate
from cylsfm.odometry.bundle.matching import epipolar_angles, match_pair

pytest.importorskip("gtsam")


def test_cylinder_and_equirectangular_keypoints_are_the_closed_forms_bearings():
    uv = torch.tensor(
        [[0.0, 0.0], [100.3, 20.7], [255.0, 63.0], [511.0, 127.0], [400.5, 5.25]], dtype=torch.float64
    )
    cyl = CylindricalCamera.full(512, 128)
    theta = (uv[:, 0] - cyl.cx) / cyl.fx
    h = (uv[:, 1] - cyl.cy) / cyl.fy
    closed = torch.stack((torch.sin(theta), h, torch.cos(theta)), 1)
    closed = closed / closed.norm(dim=1, keepdim=True)
    torch.testing.assert_close(pixel_bearings(cyl, uv), closed)
    torch.testing.assert_close(bearing_pixels(cyl, 3.0 * closed), uv)
    eq = EquirectangularCamera.full(512, 256)
    # x_e = W (theta / 2 pi + 1/2) - 1/2, y_e = H (phi / pi + 1/2) - 1/2 (docs/conventions.md)
    theta = 2 * math.pi * ((uv[:, 0] + 0.5) / 512 - 0.5)
    phi = math.pi * ((uv[:, 1] + 0.5) / 256 - 0.5)
    closed = torch.stack(
        (torch.cos(phi) * torch.sin(theta), torch.sin(phi), torch.cos(phi) * torch.cos(theta)), 1
    )
    torch.testing.assert_close(pixel_bearings(eq, uv), closed)
    torch.testing.assert_close(bearing_pixels(eq, closed), uv)


def _ride(m: int = 24, per_frame: int = 30, seed: int = 0):
    """A curving ride of ``m`` frames about a metre apart, points beside the road each seen by up to 7
    frames: ``(true c2w [M,4,4], points [P,3], exact observations)``."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(np.r_[0.0, rng.normal(0, 0.05, m - 1)])
    c2w = np.tile(np.eye(4), (m, 1, 1))
    for j in range(m):
        c2w[j, :3, :3] = rotation_y(np.asarray(yaw[j]))
        if j:
            c2w[j, :3, 3] = c2w[j - 1, :3, 3] + c2w[j, :3, :3] @ np.array([0.0, 0.0, 1.0])
    local = np.stack(
        [
            rng.choice([-1.0, 1.0], m * per_frame) * rng.uniform(3, 8, m * per_frame),
            rng.uniform(-1.5, 2.5, m * per_frame),
            rng.uniform(-2, 2, m * per_frame),
        ],
        1,
    )
    home = np.repeat(np.arange(m), per_frame)
    points = np.einsum("nij,nj->ni", c2w[home, :3, :3], local) + c2w[home, :3, 3]
    frame, point = [], []
    for q, j0 in enumerate(home):
        for j in range(max(0, j0 - 3), min(m, j0 + 4)):
            frame.append(j)
            point.append(q)
    frame, point = np.array(frame), np.array(point)
    rel = np.einsum("nji,nj->ni", c2w[frame, :3, :3], points[point] - c2w[frame, :3, 3])
    return c2w, points, Observations(frame, point, rel / np.linalg.norm(rel, axis=1, keepdims=True))


def _perturbed(c2w: np.ndarray, seed: int = 1) -> np.ndarray:
    """The ride's steps each with a few per cent of length and a few tenths of a degree of rotation off."""
    rng = np.random.default_rng(seed)
    out = c2w.copy()
    for j in range(len(c2w) - 1):
        step = invert(c2w[j]) @ c2w[j + 1]
        step[:3, 3] *= 1 + rng.normal(0, 0.05)
        step[:3, 3] += rng.normal(0, 0.03, 3)
        step[:3, :3] = rotation_y(np.asarray(rng.normal(0, 0.005))) @ step[:3, :3]
        out[j + 1] = out[j] @ step
    return out


def _in_scale(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``est`` with its positions scaled about the first frame by the one factor that fits ``truth`` best
    (a bundle adjustment's scale is the odometry's)."""
    a, b = est[:, :3, 3] - est[0, :3, 3], truth[:, :3, 3] - truth[0, :3, 3]
    out = est.copy()
    out[:, :3, 3] = est[0, :3, 3] + a * float((a * b).sum() / (a * a).sum())
    return out


def test_exact_correspondences_recover_the_ride_from_perturbed_poses():
    truth, points, obs = _ride()
    odometry = _perturbed(truth)
    assert np.abs(odometry[:, :3, 3] - truth[:, :3, 3]).max() > 0.1  # the odometry has drifted
    cam = CylindricalCamera.full(512, 128)
    # exact bearings: a tight noise model, no outliers
    done = bundle_adjust(odometry, obs, 1 / float(cam.fx), BundleSettings(pixel_sigma=0.01, iterations=100))
    est = _in_scale(done.c2w, truth)
    np.testing.assert_allclose(est[:, :3, :3], truth[:, :3, :3], atol=1e-4)
    np.testing.assert_allclose(est[:, :3, 3], truth[:, :3, 3], atol=1e-4 * 25)  # 1e-4 of the ride's length
    assert done.inliers.all()
    scale = float(
        np.linalg.norm(est[5, :3, 3] - est[0, :3, 3])
        / np.linalg.norm(done.c2w[5, :3, 3] - done.c2w[0, :3, 3])
    )
    np.testing.assert_allclose(done.points, (points - truth[0, :3, 3]) / scale + truth[0, :3, 3], atol=1e-3)


def test_a_planted_wrong_match_is_rejected_and_changes_nothing():
    truth, _, obs = _ride(seed=2)
    odometry = _perturbed(truth, seed=3)
    wrong = obs.bearing.copy()
    n = 100
    # frame obs.frame[n] matched its keypoint to a point 3 degrees beside the right one (a repeated
    # texture): still in front, still triangulated, only wrong
    wrong[n] = rotation_y(np.asarray(math.radians(3.0))) @ wrong[n]
    bad = Observations(obs.frame, obs.point, wrong)
    settings = BundleSettings(pixel_sigma=0.05)
    done = bundle_adjust(odometry, bad, 1 / 81.5, settings)
    assert not done.inliers[n]
    assert done.inliers.sum() >= len(obs.frame) - 8  # the wrong one (and at most its point's others)
    clean = bundle_adjust(odometry, obs, 1 / 81.5, settings)
    np.testing.assert_allclose(done.c2w, clean.c2w, atol=1e-4)


def test_a_stretch_without_features_keeps_the_odometry_s_steps():
    truth, _, obs = _ride(m=30, seed=4)
    odometry = _perturbed(truth, seed=5)
    blind = (obs.frame < 12) | (obs.frame > 17)  # frames 12-17 see nothing (a wall, the sky)
    done = bundle_adjust(odometry, obs.subset(blind), 1 / 81.5, BundleSettings(pixel_sigma=0.05))
    steps = [invert(done.c2w[j]) @ done.c2w[j + 1] for j in range(29)]
    odo = [invert(odometry[j]) @ odometry[j + 1] for j in range(29)]
    # inside the stretch and into it, each step is the odometry's: nothing jumps (without the odometry's
    # steps as priors the frames without features would stay where the odometry put them, and the
    # steps into the stretch would jump by the correction of the frames before it, about 0.27 m here)
    for j in range(11, 18):
        assert np.linalg.norm(steps[j][:3, 3] - odo[j][:3, 3]) < 0.05 * np.linalg.norm(odo[j][:3, 3]), j
        assert (
            math.degrees(math.acos(np.clip((np.trace(steps[j][:3, :3].T @ odo[j][:3, :3]) - 1) / 2, -1, 1)))
            < 1.0
        )
    lengths = np.array([np.linalg.norm(s[:3, 3]) for s in steps])
    assert lengths.max() < 1.5 * np.median(lengths) and lengths.min() > 0.5 * np.median(lengths)

    # outside it the adjustment corrects the odometry's steps (each stretch in its own scale: the steps
    # without features carry the scale across with the odometry's error)
    def step_error(c2w: np.ndarray, frames: slice) -> float:
        est = _in_scale(c2w[frames], truth[frames])
        true = truth[frames]
        return float(
            np.mean(
                [
                    np.linalg.norm(
                        (invert(est[k]) @ est[k + 1])[:3, 3] - (invert(true[k]) @ true[k + 1])[:3, 3]
                    )
                    for k in range(len(true) - 1)
                ]
            )
        )

    for part in (slice(0, 12), slice(18, 30)):
        assert step_error(done.c2w, part) < 0.1 * step_error(odometry, part), part


def test_triangulation_keeps_only_points_it_can_place():
    truth, points, obs = _ride(m=8, seed=6)
    got = triangulate(truth, obs, obs.points)
    ok = np.isfinite(got[:, 0])
    assert ok.mean() > 0.9
    np.testing.assert_allclose(got[ok], points[ok], atol=1e-8)
    one = obs.subset(obs.frame == 0)  # a single view: no depth
    assert np.isnan(triangulate(truth, one, obs.points)).all()
    # two views of a point straight ahead, along the ride: no parallax, not kept
    ahead = Observations(np.array([0, 1]), np.array([0, 0]), np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))
    line = np.tile(np.eye(4), (2, 1, 1))
    line[1, 2, 3] = 1.0
    assert np.isnan(triangulate(line, ahead, 1)).all()
    # a point behind the cameras that see it is not kept
    behind = Observations(np.array([0, 1]), np.array([0, 0]), np.array([[0.6, 0.0, -0.8], [0.8, 0.0, -0.6]]))
    assert np.isnan(triangulate(line, behind, 1)).all()


def test_features_are_found_across_the_seam_and_never_under_the_mask():
    from cylsfm.odometry.bundle.features import detect

    rng = np.random.default_rng(7)
    base = (rng.random((16, 64)) * 255).astype(np.uint8)
    grey = np.kron(base, np.ones((4, 4), np.uint8))  # 64x256 of 4-pixel blocks: corners everywhere
    rgb = np.repeat(grey[..., None], 3, axis=2)
    whole = detect(rgb, wraps=True)
    assert len(whole) > 50
    assert (whole.uv[:, 0] >= -0.5).all() and (whole.uv[:, 0] < 255.5).all()
    # the panorama turned by half a turn: the same keypoints, turned, including those on the seam
    turned = detect(np.roll(rgb, 128, axis=1), wraps=True)
    back = (turned.uv[:, 0] - 128) % 256
    near = np.abs(back[:, None] - whole.uv[None, :, 0]) % 256
    near = np.minimum(near, 256 - near) + np.abs(turned.uv[:, None, 1] - whole.uv[None, :, 1])
    assert (near.min(axis=1) < 0.5).mean() > 0.9
    seam = (whole.uv[:, 0] < 4) | (whole.uv[:, 0] > 251)
    assert seam.any()  # found on the seam, where a frame that does not wrap has none
    flat = detect(rgb, wraps=False)
    assert not ((flat.uv[:, 0] < 1) | (flat.uv[:, 0] > 254)).any()
    mask = np.ones((64, 256), np.uint8)
    mask[:, 100:180] = 0
    masked = detect(rgb, wraps=True, mask=mask)
    assert len(masked) > 20 and not ((masked.uv[:, 0] > 100) & (masked.uv[:, 0] < 179)).any()


def test_an_occluder_enters_no_descriptor_and_its_outline_gives_no_keypoint():
    """An occluder moves with the camera: whatever it shows, the features are the same, and its outline
    against the scene (which would follow the camera) gives none."""
    from cylsfm.odometry.bundle.features import detect

    def rgb(grey):
        return np.repeat(grey[..., None], 3, axis=2)

    rng = np.random.default_rng(3)
    scene = np.kron((rng.random((16, 64)) * 255).astype(np.uint8), np.ones((4, 4), np.uint8))
    mask = np.ones((64, 256), np.uint8)
    mask[40:, 90:170] = 0  # a helmet's rim at the bottom of the frame
    other = scene.copy()
    other[mask == 0] = (rng.random(int((mask == 0).sum())) * 255).astype(np.uint8)
    a, b = detect(rgb(scene), True, mask), detect(rgb(other), True, mask)
    assert len(a) > 20
    np.testing.assert_array_equal(a.uv, b.uv)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)
    for y, x in ((44, 100), (48, 130), (52, 150)):
        mask[y : y + 6, x : x + 6] = 1  # gaps in the mount, the scene seen through them
    plain = np.full((64, 256), 60, np.uint8)  # nothing to see but the occluder's outline
    assert len(detect(rgb(plain), True, mask, contrast=0.01)) == 0


def test_keypoints_are_where_the_blobs_are_to_a_few_hundredths_of_a_pixel():
    """SIFT's keypoints in our pixel convention (integer values are pixel centres), without OpenCV's
    default quarter-pixel shift, which would tilt every bearing of a row."""
    from cylsfm.odometry.bundle.features import detect

    rng = np.random.default_rng(0)
    h, w = 128, 512
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    grey = np.full((h, w), 128.0)
    centres = []
    for cy in range(20, h - 20, 30):
        for cx in range(0, w, 32):  # across the seam too
            x0, y0, s = cx + rng.uniform(-0.5, 0.5), cy + rng.uniform(-0.5, 0.5), rng.uniform(2.0, 3.5)
            for shift in (-w, 0, w):
                grey += rng.choice([-90, 90]) * np.exp(
                    -((xx - x0 - shift) ** 2 + (yy - y0) ** 2) / (2 * s * s)
                )
            centres.append((x0 % w, y0))
    rgb = np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    found = detect(rgb, wraps=True, contrast=0.01)
    centres = np.array(centres)
    du = found.uv[:, None, 0] - centres[None, :, 0]
    du = (du + w / 2) % w - w / 2
    dist = np.hypot(du, found.uv[:, None, 1] - centres[None, :, 1])
    near = dist.argmin(1)
    close = dist.min(1) < 1.0
    assert close.sum() > 0.8 * len(centres)
    offset = np.stack([du[close, near[close]], found.uv[close, 1] - centres[near[close], 1]], 1)
    assert np.abs(np.median(offset, axis=0)).max() < 0.05


def test_matches_keep_what_fits_the_odometry_and_tracks_drop_contradictions():
    from cylsfm.odometry.bundle.features import Features
    from cylsfm.odometry.bundle.matching import epipolar_angles, match_pair, tracks_of

    truth, _, obs = _ride(m=2, per_frame=40, seed=8)
    rel = invert(truth[1]) @ truth[0]  # T_{0->1}
    # the keypoints of both frames: every point seen by both, described by a random descriptor each
    both = np.intersect1d(obs.point[obs.frame == 0], obs.point[obs.frame == 1])
    desc = np.random.default_rng(9).random((obs.points, 128)).astype(np.float32)
    b0 = np.stack([obs.bearing[(obs.frame == 0) & (obs.point == q)][0] for q in both])
    b1 = np.stack([obs.bearing[(obs.frame == 1) & (obs.point == q)][0] for q in both])
    assert np.abs(epipolar_angles(b0, b1, rel)).max() < 1e-9  # the true matches lie on their planes
    # a planted wrong pair: keypoint 0's descriptor given to keypoint 5 of the other frame
    d1 = desc[both].copy()
    d1[[0, 5]] = d1[[5, 0]]
    n = len(both)
    none = (np.zeros((n, 2)), np.zeros((n, 3), np.uint8))
    found = match_pair(Features(none[0], desc[both], none[1]), Features(none[0], d1, none[1]), b0, b1, rel)
    pairs = {tuple(p) for p in found.tolist()}
    assert (0, 5) not in pairs and (5, 0) not in pairs  # off the epipolar plane: rejected
    assert len(pairs) == len(both) - 2 and all(k == l for k, l in pairs)
    # tracks: 0-1-2 chained into one; a chain that reaches two keypoints of one frame is dropped
    bearings = [np.eye(3)[:2], np.eye(3)[:2], np.eye(3)[:2]]
    good = tracks_of({(0, 1): np.array([[0, 0]]), (1, 2): np.array([[0, 0]])}, bearings)
    assert sorted(good.frame.tolist()) == [0, 1, 2] and good.points == 1
    bad = tracks_of({(0, 1): np.array([[0, 0], [1, 1]]), (1, 2): np.array([[0, 0], [1, 0]])}, bearings)
    assert bad.points == 0


def _brute_force_guided(da, db, ba, bb, rel, ratio, tau):
    """What guided matching means, pair by pair: a keypoint of ``b`` may match one of ``a`` when it lies
    within ``tau`` of that keypoint's epipolar half-plane (any, near the direction of travel); the ratio
    is to the nearer of the second candidate and the match's nearest look-alike in ``b``."""
    rot, t = rel[:3, :3], rel[:3, 3] / np.linalg.norm(rel[:3, 3])
    na, nb = np.cross(t, ba @ rot.T), np.cross(t, bb)  # the half-planes' normals, |n| = sin(alpha)
    off = np.abs(na @ bb.T) / np.linalg.norm(na, axis=1)[:, None]  # sin of the angle off a's plane
    same_side = (na @ nb.T) >= 0
    fits = (np.linalg.norm(nb, axis=1)[None] <= math.sin(tau)) | ((off <= math.sin(tau)) & same_side)
    dist = ((da[:, None] - db[None]) ** 2).sum(-1)
    dist[~fits] = np.inf
    order = np.sort(dist, axis=1)
    near = dist.argmin(1)
    own = ((db[:, None] - db[None]) ** 2).sum(-1) + np.diag(np.full(len(db), np.inf))
    second = np.minimum(order[:, 1], own.min(1)[near])
    rows = np.arange(len(da))
    ok = np.isfinite(order[:, 0]) & (order[:, 0] < ratio**2 * second) & (dist.argmin(0)[near] == rows)
    found = np.stack([rows[ok], near[ok]], 1)
    return found[epipolar_angles(ba[found[:, 0]], bb[found[:, 1]], rel) <= tau]


def test_guided_matching_compares_only_what_lies_near_the_epipolar_half_plane():
    """Blocks of keypoints sorted around the direction of travel give exactly the matches of comparing
    every pair inside the band (all around the sphere, across the seam, near the epipoles); a look-alike
    off the plane no longer hides a keypoint's match, as it does for the ratio over the whole frame, but a
    keypoint that has look-alikes in its own frame is never taken for a match it resembles."""
    from cylsfm.odometry.bundle.features import Features

    rng = np.random.default_rng(4)
    n = 400
    ba = rng.normal(size=(n, 3))
    ba[:6] = [[0.3, -0.2, 0.9]] * 3 + [[-0.3, 0.2, -0.9]] * 3  # at the epipoles of the travel below
    ba += rng.normal(0, 1e-3, ba.shape)
    ba /= np.linalg.norm(ba, axis=1, keepdims=True)
    rel = np.eye(4)
    rel[:3, :3] = rotation_y(np.asarray(0.4)) @ _rotation_x(0.1)
    rel[:3, 3] = rel[:3, :3] @ -np.array([0.3, -0.2, 0.9])  # T_{a->b}: travelling along (0.3, -0.2, 0.9)
    world = ba * rng.uniform(2, 10, (n, 1))
    bb = world @ rel[:3, :3].T + rel[:3, 3]
    bb = bb / np.linalg.norm(bb, axis=1, keepdims=True) + rng.normal(0, 0.01, bb.shape)  # half a degree off
    bb /= np.linalg.norm(bb, axis=1, keepdims=True)
    da = rng.random((n, 128)).astype(np.float32)
    db = da + rng.normal(0, 0.05, da.shape).astype(np.float32)
    # look-alikes: a copy of keypoint k's descriptor at a random bearing of b, for the first 150, and of
    # keypoints 150-155 at b's epipoles, which lie on every half-plane
    ahead = rel[:3, :3] @ np.array([0.3, -0.2, 0.9])  # the direction of travel in b's axes
    alike = np.concatenate([rng.normal(size=(150, 3)), [ahead] * 3, [-ahead] * 3])
    alike += rng.normal(0, 1e-3, alike.shape)
    bb = np.concatenate([bb, alike / np.linalg.norm(alike, axis=1, keepdims=True)])
    db = np.concatenate([db, da[:156] + rng.normal(0, 0.05, (156, 128)).astype(np.float32)])
    # keypoints 156-165 of a: their matches not found in b, which has two windows alike instead (nearer to
    # each other than to a's), one in the band and one elsewhere: a guess, never a match
    lost = np.arange(156, 166)
    base = da[lost].copy()
    da[lost] = base + rng.normal(0, 0.1, base.shape).astype(np.float32)
    db[lost] = rng.random((len(lost), 128)).astype(np.float32)
    elsewhere = rng.normal(size=(len(lost), 3))
    bb = np.concatenate([bb, bb[lost], elsewhere / np.linalg.norm(elsewhere, axis=1, keepdims=True)])
    windows = np.concatenate([base, base]) + rng.normal(0, 0.01, (2 * len(lost), 128)).astype(np.float32)
    db = np.concatenate([db, windows])
    none_a, none_b = np.zeros((n, 2)), np.zeros((len(db), 2))
    a, b = Features(none_a, da, none_a.astype(np.uint8)), Features(none_b, db, none_b.astype(np.uint8))
    tau = math.radians(2.0)
    found = match_pair(a, b, ba, bb, rel, 0.8, 2.0, block=16)
    want = _brute_force_guided(da.astype(np.float64), db.astype(np.float64), ba, bb, rel, 0.8, tau)
    assert {tuple(p) for p in found.tolist()} == {tuple(p) for p in want.tolist()}
    right = found[:, 0] == found[:, 1]
    assert right.mean() > 0.97 and right.sum() > 0.9 * n
    # compared over the whole frame, a look-alike spoils the ratio: most of the first 150 are lost
    dist = ((da[:, None].astype(np.float64) - db[None]) ** 2).sum(-1)
    two = np.sort(dist, axis=1)[:, :2]
    assert (two[:150, 0] < 0.64 * two[:150, 1]).mean() < 0.2
    assert np.isin(np.arange(6, 150), found[right, 0]).mean() > 0.9
    assert not np.isin(np.arange(150, 156), found[:, 0]).any()  # an epipole's look-alike competes with all
    assert not np.isin(lost, found[:, 0]).any()


def test_the_bundle_stage_corrects_a_poor_odometry_and_a_second_run_reuses_it(ckpt, tmp_path, monkeypatch):
    """An untrained model's depth makes a poor refinement; the adjustment of SIFT features across the frames
    corrects its rotations and its path. Run again, the adjustment is read from the state, not redone; a
    run killed during the adjustment continues to the same trajectory."""
    import json

    import cylsfm
    from cylsfm.data.synth import generate_dataset
    from cylsfm.odometry import OdometrySettings

    generate_dataset(
        tmp_path / "data", sequences=1, frames=16, width=256, height=64, seed=3, workers=1, progress=False
    )
    seq = tmp_path / "data" / "seq_000"
    opt = OdometrySettings(refine=True, bundle=True, device="cpu", progress=False)
    first = cylsfm.odometry(seq, ckpt, tmp_path / "out", opt)
    adjusted, refined = first.metrics["bundle adjusted"], first.metrics["refined"]
    assert adjusted["rot_err_deg_mean"] < 0.5 * refined["rot_err_deg_mean"]
    assert adjusted["ape_rmse"] < refined["ape_rmse"]
    summary = json.loads((tmp_path / "out" / "odometry.json").read_text())["bundle"]
    assert summary["points"] > 100 and summary["kept"] > 0.8 * summary["observations"]
    assert "bundle adjusted" in (tmp_path / "out" / "trajectory.txt").read_text()
    # the trajectory written is the adjusted one
    from cylsfm.data.io import read_tum
    from cylsfm.evaluate.pose_metrics import trajectory_metrics

    times, truth = read_tum(seq / "poses.txt")
    assert trajectory_metrics(truth, times, first.c2w, times)[0]["ape_rmse"] == pytest.approx(
        adjusted["ape_rmse"]
    )
    assert "bundle adjustment" in first.timings
    # the triangulated points, coloured, as a PLY point cloud
    from plyfile import PlyData

    cloud = PlyData.read(str(tmp_path / "out" / "points.ply"))["vertex"]
    assert len(cloud) == summary["points"]
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1)
    assert np.isfinite(xyz).all() and np.ptp(xyz, axis=0).max() > 1.0
    assert np.stack([cloud["red"], cloud["green"], cloud["blue"]], 1).std() > 5  # the frames' colours
    _exports_use_the_triangulated_points(seq, ckpt, tmp_path, opt, summary)
    again = cylsfm.odometry(seq, ckpt, tmp_path / "out", opt)
    assert "bundle adjustment" not in again.timings
    np.testing.assert_array_equal(again.c2w, first.c2w)
    from cylsfm.odometry.bundle import stage

    monkeypatch.setattr(stage, "METHOD", stage.METHOD + 1)  # a newer method: adjusted again
    assert "bundle adjustment" in cylsfm.odometry(seq, ckpt, tmp_path / "out", opt).timings
    monkeypatch.undo()
    # killed during the adjustment (the tracking saved), then run again: the same trajectory
    real = stage.bundle_adjust

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(stage, "bundle_adjust", killed)
    with pytest.raises(KeyboardInterrupt):
        cylsfm.odometry(seq, ckpt, tmp_path / "killed", opt)
    assert not (tmp_path / "killed" / "trajectory.txt").exists()
    monkeypatch.setattr(stage, "bundle_adjust", real)
    resumed = cylsfm.odometry(seq, ckpt, tmp_path / "killed", opt)
    assert "pose network" not in resumed.timings  # the tracking was not done again
    np.testing.assert_allclose(resumed.c2w, first.c2w, atol=1e-9)


def _exports_use_the_triangulated_points(seq, ckpt, tmp_path, opt, summary):
    """``export colmap`` of the adjusted run writes its triangulated points with the keypoints that saw
    them: a real reprojection error (neither zero, as for points made from the depth, nor large)."""
    pytest.importorskip("pycolmap")
    import pycolmap

    from cylsfm.errors import CylsfmError
    from cylsfm.odometry.exports import export_colmap
    from cylsfm.odometry.points import read_points

    points = read_points(tmp_path / "out" / "points.npz", 16, (256, 64))
    assert len(points.xyz) == summary["points"] and len(points.frame) == summary["kept"]
    done = export_colmap(seq, ckpt, tmp_path / "colmap", opt, odometry=tmp_path / "out")
    rec = pycolmap.Reconstruction(str(tmp_path / "colmap" / "sparse" / "0"))
    assert done["points_from"] == "bundle adjustment"
    assert 0.8 * summary["points"] <= rec.num_points3D() == done["points"] <= summary["points"]
    assert 0.01 < rec.compute_mean_reprojection_error() < 1.5  # pixels of the 512-pixel views
    assert rec.compute_mean_track_length() >= 2
    # each point is where the adjustment put it
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    nearest = np.abs(xyz[:, None] - points.xyz[None]).sum(-1).min(1)
    assert nearest.max() < 1e-9
    # a points file that does not fit the ride is refused, naming it
    bad = tmp_path / "bad.npz"
    np.savez(bad, xyz=points.xyz, rgb=points.rgb, frame=points.frame + 16, point=points.point, uv=points.uv,
             unit=np.array("x"))  # fmt: skip
    with pytest.raises(CylsfmError, match=r"bad\.npz: observations of frames or points that do not exist"):
        read_points(bad, 16, (256, 64))


def test_a_ride_without_texture_keeps_the_odometry(ckpt, tmp_path):
    """Frames with nothing to match (one flat grey): no feature, no track, and the odometry's poses are kept
    as they are, without an error."""
    import cylsfm
    from cylsfm.data.format import SequenceWriter
    from cylsfm.odometry import OdometrySettings
    from cylsfm.odometry.bundle.features import detect

    grey = np.full((32, 128, 3), 128, np.uint8)
    assert len(detect(grey, wraps=True)) == 0
    writer = SequenceWriter(tmp_path / "flat", CylindricalCamera.full(128, 32))
    for _ in range(6):
        writer.add_frame(grey)
    seq = writer.finish()
    opt = OdometrySettings(device="cpu", progress=False, loops=False)
    plain = cylsfm.odometry(seq, ckpt, tmp_path / "plain", opt)
    from dataclasses import replace

    adjusted = cylsfm.odometry(seq, ckpt, tmp_path / "adjusted", replace(opt, bundle=True))
    np.testing.assert_allclose(adjusted.c2w, plain.c2w, atol=1e-12)
    import json

    summary = json.loads((tmp_path / "adjusted" / "odometry.json").read_text())["bundle"]
    assert summary["tracks"] == 0 and summary["rounds"] == 0
    # exported, the model still has points to start a splat from: the depth's
    pytest.importorskip("pycolmap")
    from cylsfm.odometry.exports import export_colmap

    done = export_colmap(
        seq, ckpt, tmp_path / "colmap", replace(opt, bundle=True), odometry=tmp_path / "adjusted"
    )
    assert done["points_from"] == "depth" and done["points"] > 0


def test_a_pair_s_relative_pose_is_corrected_from_its_matches_with_the_odometry_s_length():
    from cylsfm.odometry.bundle.matching import epipolar_angles, relative_pose

    truth, _, obs = _ride(m=2, per_frame=60, seed=10)
    both = np.intersect1d(obs.point[obs.frame == 0], obs.point[obs.frame == 1])
    b0 = np.stack([obs.bearing[(obs.frame == 0) & (obs.point == q)][0] for q in both])
    b1 = np.stack([obs.bearing[(obs.frame == 1) & (obs.point == q)][0] for q in both])
    rel = invert(truth[1]) @ truth[0]  # T_{0->1}
    # the odometry: 3 degrees off in yaw, 1 in pitch, the direction of travel 10 degrees off, 40% too long
    odo = rel.copy()
    turn = rotation_y(np.asarray(math.radians(3.0))) @ _rotation_x(math.radians(1.0))
    odo[:3, :3] = turn @ rel[:3, :3]
    odo[:3, 3] = 1.4 * rotation_y(np.asarray(math.radians(10.0))) @ rel[:3, 3]
    scale = 2 * 0.3 / 81.5
    got = relative_pose(b0, b1, odo, scale)
    np.testing.assert_allclose(got[:3, :3], rel[:3, :3], atol=1e-6)
    length = np.linalg.norm(odo[:3, 3])
    np.testing.assert_allclose(np.linalg.norm(got[:3, 3]), length, rtol=1e-9)  # the odometry's length
    np.testing.assert_allclose(got[:3, 3] / length, rel[:3, 3] / np.linalg.norm(rel[:3, 3]), atol=1e-6)
    # a sixth of the matches wrong (another point's keypoint, clearly off its epipolar plane): ignored
    wrong = b1.copy()
    bad = np.arange(0, len(both), 5)
    wrong[bad] = b1[np.roll(bad, 1)]
    bad = bad[epipolar_angles(b0[bad], wrong[bad], rel) > math.radians(2.0)]
    assert len(bad) >= len(both) // 6
    wrong = np.where(np.isin(np.arange(len(both)), bad)[:, None], wrong, b1)
    robust = relative_pose(b0, wrong, odo, scale)
    np.testing.assert_allclose(robust, got, atol=1e-6)
    # a camera that did not move: the rotation alone is found
    still = np.eye(4)
    still[:3, :3] = rel[:3, :3]
    turned = b0 @ rel[:3, :3].T
    odo_still = np.eye(4)
    odo_still[:3, :3] = turn @ rel[:3, :3]
    np.testing.assert_allclose(relative_pose(b0, turned, odo_still, scale), still, atol=1e-6)


def _rotation_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@pytest.mark.parametrize("case", ["two frames", "still camera", "all masked"])
def test_bad_rides_for_the_adjustment_keep_the_odometry_or_say_why(ckpt, tmp_path, capsys, case):
    """A ride of two frames, a camera that never moves, a mask over everything: ``--bundle`` either keeps
    the odometry's poses or stops with a one-line error naming the input; never a traceback, and an earlier
    output in the folder is kept whole."""
    from PIL import Image

    from cylsfm.cli import main
    from cylsfm.data.format import SequenceWriter
    from cylsfm.data.synth import generate_dataset

    generate_dataset(
        tmp_path / "data", sequences=1, frames=6, width=128, height=32, seed=5, workers=1, progress=False
    )
    src = tmp_path / "data" / "seq_000"
    frames = sorted((src / "images").glob("*.png"))
    writer = SequenceWriter(tmp_path / "ride", CylindricalCamera.full(128, 32))
    chosen = {"two frames": frames[:2], "still camera": [frames[0]] * 6, "all masked": frames}[case]
    for f in chosen:
        writer.add_frame(np.asarray(Image.open(f).convert("RGB")))
    ride = writer.finish()
    args = ["odometry", str(ride), "--checkpoint", str(ckpt), "--device", "cpu", "--no-progress", "--refine"]
    if case == "all masked":
        Image.fromarray(np.zeros((32, 128), np.uint8)).save(tmp_path / "mask.png")
        args += ["--mask", str(tmp_path / "mask.png")]
    plain = main([*args, "--out", str(tmp_path / "plain")])
    capsys.readouterr()
    out = tmp_path / "adjusted"
    out.mkdir()
    (out / "keep.txt").write_text("earlier")
    code = main([*args, "--out", str(out), "--bundle"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert (out / "keep.txt").read_text() == "earlier"
    if code != 0:
        assert err.startswith("cylsfm odometry: error:") and len(err.strip().splitlines()) == 1, err
        assert plain != 0  # refused only what the odometry itself refuses
        return
    assert plain == 0
    from cylsfm.data.io import read_tum

    _, before = read_tum(tmp_path / "plain" / "trajectory.txt")
    _, after = read_tum(out / "trajectory.txt")
    assert np.isfinite(after).all() and after.shape == before.shape
    if case != "two frames":  # nothing to triangulate (no parallax, no feature): the odometry's poses
        np.testing.assert_allclose(after, before, atol=1e-6)
