"""Each frame's depth brought to the ride's adjusted points (cylsfm.odometry.depth.point_factors), and the
odometry's depth files in the trajectory's one scale by construction."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from cylsfm.data.geometry import ride_geometry
from cylsfm.data.points import SparsePoints
from cylsfm.geometry import CylindricalCamera
from cylsfm.odometry.depth import MIN_POINTS, point_factors

FRAMES = CylindricalCamera.full(256, 64)  # the ride's own frames
VIEW = CylindricalCamera.full(128, 32)  # the network's depth maps


def _ride(frames: int = 8, points: int = 300, seed: int = 0):
    """A camera driving forward among points 3-9 m away, every point seen by every frame it projects in:
    poses ``[M,4,4]`` and the points with their tracks at FRAMES' pixels."""
    rng = np.random.default_rng(seed)
    c2w = np.tile(np.eye(4), (frames, 1, 1))
    c2w[:, 2, 3] = 0.4 * np.arange(frames)
    angle = rng.uniform(-math.pi, math.pi, points)
    dist = rng.uniform(3.0, 9.0, points)
    xyz = np.stack([dist * np.sin(angle), rng.uniform(-1.0, 1.0, points), dist * np.cos(angle) + 1.4], 1)
    tracks = []
    for j in range(frames):
        local = xyz - c2w[j, :3, 3]
        uv = FRAMES.project(torch.from_numpy(local).T[None, :, :, None])[0, :, :, 0].T.numpy()
        uv[:, 0] = (uv[:, 0] + 0.5) % FRAMES.width - 0.5
        inside = (uv[:, 1] > -0.5) & (uv[:, 1] < FRAMES.height - 0.5)
        tracks += [[j, p, *uv[p]] for p in np.nonzero(inside)[0]]
    tracks = np.array(tracks)
    pts = SparsePoints(
        xyz, np.zeros((points, 3), np.uint8), tracks[:, 0].astype(np.int64), tracks[:, 1].astype(np.int64),
        tracks[:, 2:], "network units",
    )  # fmt: skip
    return c2w, pts


def _maps(geometry, scale: np.ndarray, outliers: dict[int, float] | None = None, seed: int = 1):
    """Each frame's depth map at VIEW's size: the true depth of the points it sees times ``scale[j]``
    where they fall (the nearest where two fall in one pixel), 0 elsewhere; ``outliers``: frame -> the
    share of its points whose map value is 3x wrong."""
    rng = np.random.default_rng(seed)
    grid = torch.from_numpy(geometry.local).T[None, :, :, None]
    uv = VIEW.project(grid)[0, :, :, 0].T.numpy()
    depth = VIEW.depth_of(grid)[0, 0, :, 0].numpy()
    maps = np.zeros((len(geometry.c2w), VIEW.height, VIEW.width), np.float32)
    for n in range(len(uv)):
        j = geometry.frame[n]
        value = depth[n] * scale[j]
        if outliers and rng.random() < outliers.get(j, 0.0):
            value *= 3.0
        row, col = round(float(uv[n, 1])), round(float(uv[n, 0])) % VIEW.width
        if 0 <= row < VIEW.height and not 0 < maps[j, row, col] < value:
            maps[j, row, col] = value
    return maps


def test_each_frame_is_brought_to_its_points_despite_outliers_and_gaps():
    """A depth whose scale wanders from frame to frame (+-25%) comes back in the points' one scale; a third
    of a frame's points 3x off move nothing; a frame that sees too few points takes its neighbours'
    factor (geometric mean), the ends their nearest measured frame's."""
    c2w, pts = _ride()
    keep = (pts.frame != 3) | (np.arange(len(pts.frame)) % 40 == 0)  # frame 3 sees a handful
    keep &= pts.frame != 7  # the last frame sees none
    pts = SparsePoints(pts.xyz, pts.rgb, pts.frame[keep], pts.point[keep], pts.uv[keep], pts.unit)
    geo = ride_geometry(c2w, pts, FRAMES)
    wander = np.array([1.0, 1.25, 0.8, 1.1, 0.9, 1.2, 0.75, 1.05])
    maps = _maps(geo, wander, outliers={5: 0.3})
    found = point_factors(geo, VIEW, lambda j: maps[j])
    assert found.points[3] < MIN_POINTS and found.points[7] == 0
    measured = [0, 1, 2, 4, 5, 6]
    assert (found.points[measured] >= 100).all()
    np.testing.assert_allclose(found.factors[measured], 1 / wander[measured], rtol=1e-6)
    assert found.factors[3] == pytest.approx(math.sqrt(found.factors[2] * found.factors[4]))
    assert found.factors[7] == pytest.approx(found.factors[6])
    # the depth maps times their factors: one scale over the ride
    summary = found.to_dict()
    assert summary["frames_measured"] == 6 and len(summary["factors"]) == 8
    assert summary["factor_cv"] > 0.1  # the wander it took out
    json.dumps(summary)


def test_points_weigh_by_their_parallax_and_no_points_leave_the_base_factor():
    """Points of little parallax (large sigma) weigh less than well-triangulated ones; a ride whose frames
    see too few points keeps the base factor (the one to metres, or 1) everywhere."""
    c2w, pts = _ride(frames=3)
    geo = ride_geometry(c2w, pts, FRAMES)
    weak = geo.sigma > np.median(geo.sigma)  # the worse-triangulated half
    maps = _maps(geo, np.ones(3))
    grid = torch.from_numpy(geo.local).T[None, :, :, None]
    uv = VIEW.project(grid)[0, :, :, 0].T.numpy()
    for n in np.nonzero(weak & (geo.frame == 1))[0]:  # where only weak points fall, the map 2x off
        row, col = round(float(uv[n, 1])), round(float(uv[n, 0])) % VIEW.width
        if 0 <= row < VIEW.height:
            maps[1, row, col] *= 2.0
    found = point_factors(geo, VIEW, lambda j: maps[j])
    assert found.factors[1] == pytest.approx(1.0, abs=0.05)  # the strong half decides
    few = SparsePoints(pts.xyz, pts.rgb, pts.frame[:10], pts.point[:10], pts.uv[:10], pts.unit)
    none = point_factors(ride_geometry(c2w, few, FRAMES), VIEW, lambda j: maps[j], base=2.5)
    np.testing.assert_array_equal(none.factors, 2.5)


def test_odometry_depth_files_share_the_trajectory_s_scale(ckpt, tmp_path, monkeypatch):
    """The ride's true depth given to the refinement, but wandering +-20% in scale from frame to frame (as a
    network's does): with the bundle adjustment the depth files written keep one scale over the ride (the
    per-frame median ratio to the truth steady to 2%), in the trajectory's unit; without it they keep the
    wander."""
    from cylsfm.data.format import load_depth
    from cylsfm.data.synth import generate_dataset
    from cylsfm.geometry.photometric import resize_depth
    from cylsfm.odometry import OdometrySettings, odometry
    from cylsfm.odometry.depth import DepthSource

    generate_dataset(
        tmp_path / "data", sequences=1, frames=16, width=256, height=64, seed=3, workers=1, progress=False
    )
    seq = tmp_path / "data" / "seq_000"
    true = DepthSource._true
    wander = 1.0 + 0.2 * np.sin(1.3 * np.arange(16))
    monkeypatch.setattr(DepthSource, "_true", lambda self, i: true(self, i) * float(wander[i]))

    def spread(out):
        ratios = []
        for stem in sorted(p.stem for p in (out / "depth").glob("*.npy")):
            file = load_depth(out / "depth" / f"{stem}.npy")
            gt = load_depth(seq / "depth" / f"{stem}.npy")
            gt = resize_depth(torch.from_numpy(gt)[None, None], file.shape)[0, 0].numpy()
            ok = (file > 0) & (gt > 0) & (gt < 80)
            ratios.append(np.median(gt[ok] / file[ok]))
        ratios = np.array(ratios)
        return ratios.std() / ratios.mean(), len(ratios)

    base = dict(refine=True, depth_from=tmp_path / "data", save_depth_maps=True, device="cpu", progress=False)
    adjusted = odometry(seq, ckpt, tmp_path / "bundle", OdometrySettings(bundle=True, **base))
    cv, n = spread(tmp_path / "bundle")
    assert n == 16 and cv < 0.02
    summary = json.loads((tmp_path / "bundle" / "odometry.json").read_text())["depth_scale"]
    assert summary["frames_measured"] >= 14 and summary["factor_cv"] > 0.1
    np.testing.assert_allclose(np.array(summary["factors"]) * wander, 1.0, rtol=0.03)  # the wander undone
    assert not (tmp_path / "bundle" / ".odometry-depth").exists()
    assert adjusted.depth == tmp_path / "bundle" / "depth"
    odometry(seq, ckpt, tmp_path / "plain", OdometrySettings(bundle=False, **base))
    assert spread(tmp_path / "plain")[0] > 0.1
    assert json.loads((tmp_path / "plain" / "odometry.json").read_text())["depth_scale"] is None


def test_predict_writes_each_frame_in_the_odometry_s_scale(ckpt, tmp_path):
    """``predict --odometry``: each frame's depth times its own factor to the odometry's adjusted points;
    an odometry without the adjustment, another checkpoint, or a camera height beside
    it is refused with a message naming the file, before anything is written."""
    from cylsfm.data.format import load_depth
    from cylsfm.data.synth import generate_dataset
    from cylsfm.errors import InputError
    from cylsfm.odometry import OdometrySettings, odometry
    from cylsfm.predict import predict
    from helpers import untrained_checkpoint

    generate_dataset(
        tmp_path / "data", sequences=1, frames=12, width=256, height=64, seed=4, workers=1, progress=False
    )
    seq = tmp_path / "data" / "seq_000"
    base = dict(refine=True, save_depth_maps=True, device="cpu", progress=False)
    odometry(seq, ckpt, tmp_path / "odo", OdometrySettings(bundle=True, **base))
    factors = json.loads((tmp_path / "odo" / "odometry.json").read_text())["depth_scale"]["factors"]
    assert len(factors) == 12 and np.std(factors) > 0
    predict(ckpt, [seq / "images"], tmp_path / "pred", device="cpu", png=False, progress=False,
            odometry=tmp_path / "odo")  # fmt: skip
    predict(ckpt, [seq / "images"], tmp_path / "raw", device="cpu", png=False, progress=False)
    stems = sorted(p.stem for p in (tmp_path / "odo" / "depth").glob("*.npy"))
    assert len(stems) == 12
    for stem, factor in zip(stems, factors, strict=True):  # each frame times its own factor
        ours = load_depth(tmp_path / "pred" / "images" / f"{stem}.npy")
        np.testing.assert_allclose(
            ours, load_depth(tmp_path / "raw" / "images" / f"{stem}.npy") * factor, rtol=1e-5
        )
    scale = json.loads((tmp_path / "pred" / "images" / "scale.json").read_text())
    assert scale["factors"] == pytest.approx(factors) and "adjusted points" in scale["note"]

    odometry(seq, ckpt, tmp_path / "plain", OdometrySettings(bundle=False, **base))
    other = untrained_checkpoint(tmp_path / "other", 256, 64)
    for given, kwargs, message in [
        (tmp_path / "plain", {}, r"plain.odometry\.json: has no per-frame depth scale"),
        (tmp_path / "odo", {"camera_height": 1.5}, "without camera_height"),
        (tmp_path / "missing", {}, r"missing.odometry\.json: not found"),
    ]:
        with pytest.raises(InputError, match=message):
            predict(ckpt, [seq / "images"], tmp_path / "p2", device="cpu", png=False, progress=False,
                    odometry=given, **kwargs)  # fmt: skip
    assert not (tmp_path / "p2").exists()  # refused before anything is written
    with pytest.raises(InputError, match="another checkpoint"):
        predict(other, [seq / "images"], tmp_path / "p3", device="cpu", png=False, progress=False,
                odometry=tmp_path / "odo")  # fmt: skip
