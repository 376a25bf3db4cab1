"""A ride's own adjusted geometry as training targets (cylsfm.data.geometry) and in the dataset's samples."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cylsfm.data import SampleOptions, SequenceDataset, build_index
from cylsfm.data.augment import AugmentConfig
from cylsfm.data.geometry import DEPTH_FLOOR, load_geometry
from cylsfm.data.io import DatasetError, write_tum
from cylsfm.geometry import CylindricalCamera
from cylsfm.odometry.points import write_points

CAM = CylindricalCamera.full(64, 16)


def _yaw(deg: float, x: float, z: float) -> np.ndarray:
    a = math.radians(deg)
    m = np.eye(4)
    m[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    m[:3, 3] = [x, 0.0, z]
    return m


def _ride(frames: int = 6, points: int = 40, seed: int = 0, camera=CAM, c2w=None):
    """A camera driving forward and turning a little among points 3-9 m away: its poses ``[M,4,4]``,
    the points ``[P,3]`` and every observation ``[N,4]`` (frame, point, u, v) at CAM's pixels."""
    rng = np.random.default_rng(seed)
    if c2w is None:
        c2w = np.stack([_yaw(2.0 * j, 0.1 * j, 0.5 * j) for j in range(frames)])
    angle = rng.uniform(-math.pi, math.pi, points)
    dist = rng.uniform(3.0, 9.0, points)
    xyz = np.stack([dist * np.sin(angle), rng.uniform(-1.0, 1.0, points), dist * np.cos(angle) + 1.0], 1)
    xyz = xyz @ c2w[0, :3, :3].T + c2w[0, :3, 3]  # around the first frame
    tracks = []
    for j in range(frames):
        local = (xyz - c2w[j, :3, 3]) @ c2w[j, :3, :3]  # R^T (X - c)
        uv = camera.project(torch.from_numpy(local).T[None, :, :, None])[0, :, :, 0].T.numpy()
        uv[:, 0] = (uv[:, 0] + 0.5) % camera.width - 0.5  # the seam's columns wrapped into the frame
        inside = (uv[:, 1] > -0.5) & (uv[:, 1] < camera.height - 0.5)
        tracks += [[j, p, *uv[p]] for p in np.nonzero(inside)[0]]
    return c2w, xyz, np.array(tracks, dtype=np.float64)


def _write(folder, c2w, xyz, tracks) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    write_tum(folder / "trajectory.txt", np.arange(len(c2w)), c2w, ["unit: network units"])
    write_points(folder, xyz, np.zeros((len(xyz), 3), np.uint8), tracks, "network units")


def test_depth_relative_poses_and_sigma_against_the_closed_form(tmp_path):
    c2w, xyz, tracks = _ride()
    _write(tmp_path / "ride", c2w, xyz, tracks)
    geo = load_geometry(tmp_path / "ride", len(c2w), CAM)
    assert len(geo.frame) == len(tracks)  # every observation explained
    local = np.einsum(
        "nji,nj->ni", c2w[geo.frame, :3, :3], xyz[tracks[:, 1].astype(int)] - c2w[geo.frame, :3, 3]
    )
    np.testing.assert_allclose(geo.depth, np.hypot(local[:, 0], local[:, 2]), rtol=1e-9)
    assert (geo.sigma >= DEPTH_FLOOR).all()
    rel = geo.relative(2, [1, 3])
    np.testing.assert_allclose(rel, np.linalg.inv(c2w[[1, 3]]) @ c2w[2], atol=1e-9)
    p_t = np.append(xyz[0] - 0.0, 1.0)  # a world point, through the relative pose
    cam_t = np.linalg.inv(c2w[2]) @ p_t
    np.testing.assert_allclose(rel[1] @ cam_t, np.linalg.inv(c2w[3]) @ p_t, atol=1e-9)


def test_depth_map_at_another_size_keeps_the_nearest_point_of_each_scaled_pixel(tmp_path):
    c2w, xyz, tracks = _ride(points=120)
    _write(tmp_path / "ride", c2w, xyz, tracks)
    geo = load_geometry(tmp_path / "ride", len(c2w), CAM)
    small = geo.depth_map(3, (32, 8))
    assert small.shape == (2, 8, 32) and small.dtype == np.float32
    at = geo.frame == 3
    col = np.round((geo.uv[at, 0] + 0.5) / 2 - 0.5).astype(int) % 32  # pixel centres kept, halved
    row = np.round((geo.uv[at, 1] + 0.5) / 2 - 0.5).astype(int)
    nearest: dict[tuple[int, int], float] = {}
    for r, c, d in zip(row, col, geo.depth[at], strict=True):
        nearest[(r, c)] = min(d, nearest.get((r, c), np.inf))
    assert len(nearest) < at.sum()  # some pixels have two points: the nearest is kept
    for (r, c), d in nearest.items():
        assert small[0, r, c] == pytest.approx(d, rel=1e-6) and small[1, r, c] >= DEPTH_FLOOR
    assert (small[0] > 0).sum() == len(nearest) and ((small[1] > 0) == (small[0] > 0)).all()
    assert not geo.depth_map(99, (32, 8)).any()  # a frame without points: none


def test_points_behind_or_not_where_their_keypoint_is_are_no_target(tmp_path):
    c2w, xyz, tracks = _ride()
    bad = tracks.copy()
    bad[:5, 2] = (bad[:5, 2] + CAM.width / 2) % CAM.width  # the keypoint on the other side: the point behind
    bad[5:8, 3] = np.clip(bad[5:8, 3] + 4.0, 0, CAM.height - 1)  # rows off by 4 pixels
    _write(tmp_path / "ride", c2w, xyz, bad)
    geo = load_geometry(tmp_path / "ride", len(c2w), CAM)
    moved = np.abs(bad[5:8, 3] - tracks[5:8, 3]) > 2.0
    assert len(geo.frame) == len(tracks) - 5 - int(moved.sum())


def test_a_wider_parallax_is_a_surer_depth(tmp_path):
    c2w, xyz, tracks = _ride(frames=6)
    near = tracks[tracks[:, 0] <= 1]  # each point seen from two frames 0.5 m apart
    _write(tmp_path / "two", c2w, xyz, near)
    _write(tmp_path / "all", c2w, xyz, tracks)
    two = load_geometry(tmp_path / "two", len(c2w), CAM)
    full = load_geometry(tmp_path / "all", len(c2w), CAM)
    point = near[:, 1].astype(int)
    first = {int(p): s for p, s in zip(point, two.sigma, strict=True)}
    wide = {int(p): s for p, s in zip(tracks[:, 1].astype(int), full.sigma, strict=True)}
    assert np.median([wide[p] / first[p] for p in first if p in wide]) < 0.5


@pytest.mark.parametrize(
    "damage, message",
    [
        ("no trajectory", "trajectory.txt: not found"),
        ("short trajectory", "5 poses for a ride of 6 frames"),
        ("keypoints outside", "outside the 64x16 frames"),
        ("no points", "points.npz: not found"),
        ("standing still", "does not move"),
    ],
)
def test_bad_geometry_is_named(tmp_path, damage, message):
    c2w, xyz, tracks = _ride()
    if damage == "keypoints outside":
        tracks[0, 3] = 40.0
    if damage == "standing still":
        c2w[:, :3, 3] = 0.0
    _write(tmp_path / "ride", c2w, xyz, tracks)
    if damage == "no trajectory":
        (tmp_path / "ride" / "trajectory.txt").unlink()
    if damage == "short trajectory":
        write_tum(tmp_path / "ride" / "trajectory.txt", np.arange(5), c2w[:5])
    if damage == "no points":
        (tmp_path / "ride" / "points.npz").unlink()
    with pytest.raises(DatasetError, match=message):
        load_geometry(tmp_path / "ride", len(c2w), CAM)


def _dataset(root, geometry, mirror_prob=0.0, ground_truth=False):
    index = build_index(root, None, seq_length=3)
    augment = AugmentConfig(mirror=mirror_prob > 0, mirror_prob=mirror_prob, color_jitter=False)
    options = SampleOptions(size=(32, 8), augment=augment, geometry=geometry, ground_truth=ground_truth)
    return SequenceDataset(index, options)


@pytest.fixture
def tiny(tmp_path):
    """A 2-ride synthetic dataset at 64x16 (with its ground truth)."""
    from cylsfm.data.synth import generate_dataset

    root = tmp_path / "data"
    generate_dataset(root, sequences=2, frames=6, width=64, height=16, seed=0, workers=1, progress=False)
    return root


def test_samples_carry_the_geometry_mirrored_with_the_frames(tiny, tmp_path):
    """With the ride's true trajectory as its geometry, the adjusted poses of a sample are its ground-truth
    poses, plain and mirrored; a ride without geometry has no target."""
    from cylsfm.data.io import read_tum

    seq = sorted(p for p in tiny.iterdir() if p.name.startswith("seq_"))[0]
    _, c2w = read_tum(seq / "poses.txt")
    cam = CylindricalCamera.from_json(seq / "camera.json")
    _, xyz, tracks = _ride(frames=len(c2w), camera=cam, c2w=c2w)
    geo_root = tmp_path / "geometry"
    _write(geo_root / seq.name, c2w, xyz, tracks)
    step = np.median(np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1))
    plain = None
    for mirror in (0.0, 1.0):
        data = _dataset(tiny, geo_root, mirror_prob=mirror, ground_truth=True)
        a = data[0]
        assert (
            a["sequence"] == seq.name and a["sfm_depth"].shape == (4, 8, 32) and (a["sfm_depth"][0] > 0).any()
        )
        np.testing.assert_allclose(a["sfm_step"].numpy(), [step, step], rtol=1e-5)
        torch.testing.assert_close(a["sfm_pose"], a["pose_gt"], atol=1e-5, rtol=1e-5)
        if plain is not None:  # mirrored: the depth flipped with the frames
            assert torch.equal(a["sfm_depth"], plain["sfm_depth"].flip(-1))
            assert not torch.allclose(a["sfm_pose"], plain["sfm_pose"])
        plain = a
        other = next(s for s in data if s["sequence"] != seq.name)
        assert other["sfm_step"].tolist() == [0.0, 0.0] and not other["sfm_depth"].any()


def test_depth_files_of_the_ride_give_each_frame_its_fused_depth(tmp_path):
    """With the odometry's depth files (here each frame's exact depth of a wall 6 units around the ride's
    start), every frame has its fused depth, at the files' size or the samples'; without all of them, or of
    a crop's aspect ratio, none; a damaged file is named."""
    from cylsfm.data.io import save_depth

    c2w, xyz, tracks = _ride()
    folder = tmp_path / "ride"
    _write(folder, c2w, xyz, tracks)
    small = CAM.resized(32, 8)
    rays = small.rays(small.pixel_grid(1, dtype=torch.float64))[0].numpy()
    stems = [f"{j:06d}" for j in range(len(c2w))]
    (folder / "depth").mkdir()
    truth = []
    for j, stem in enumerate(stems):
        direction = np.einsum("ij,jhw->ihw", c2w[j, :3, :3], rays)[[0, 2]]  # horizontal, in the world
        centre = c2w[j, [0, 2], 3]
        b = np.einsum("i,ihw->hw", centre, direction)
        d = -b + np.sqrt(b**2 - (centre @ centre - 36.0))
        truth.append(d.astype(np.float32))
        save_depth(folder / "depth" / f"{stem}.npy", truth[-1])
    geo = load_geometry(folder, len(c2w), CAM, stems)
    assert geo.fused is not None and geo.fused.shape == (len(c2w), 2, 8, 32)
    target = geo.targets(2, (32, 8))
    assert target.shape == (4, 8, 32)
    np.testing.assert_array_equal(target[:2], geo.depth_map(2, (32, 8)))
    known = target[2] > 0
    assert known[2:-2].all()
    np.testing.assert_allclose(target[2][known], truth[2][known], rtol=0.02)
    assert geo.targets(2, (64, 16)).shape == (4, 16, 64)  # resized to the samples' size
    assert load_geometry(folder, len(c2w), CAM).fused is None  # without the frames' names
    (folder / "depth" / f"{stems[-1]}.npy").unlink()
    assert load_geometry(folder, len(c2w), CAM, stems).fused is None  # a frame without its file
    assert not load_geometry(folder, len(c2w), CAM, stems).targets(2, (32, 8))[2:].any()
    save_depth(folder / "depth" / f"{stems[-1]}.npy", np.ones((8, 16), np.float32))
    with pytest.raises(DatasetError, match=f"{stems[-1]}.npy"):
        load_geometry(folder, len(c2w), CAM, stems)
    (folder / "depth" / f"{stems[-1]}.npy").write_bytes(b"not a depth map")
    with pytest.raises(DatasetError, match=f"{stems[-1]}.npy"):
        load_geometry(folder, len(c2w), CAM, stems)
    for stem in stems:  # a crop's maps (a model of crops): no fused depth
        save_depth(folder / "depth" / f"{stem}.npy", np.ones((8, 16), np.float32))
    assert load_geometry(folder, len(c2w), CAM, stems).fused is None
