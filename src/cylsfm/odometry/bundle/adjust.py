"""A bundle adjustment of a ride's poses and points on bearings, seeded and held by its odometry (GTSAM).

Every frame is a node ``X_j`` (camera-to-world, :class:`gtsam.Pose3`), every track a 3D point. The factors:

- the first frame fixed where the odometry puts it;
- one between consecutive frames from the odometry's step (``X_j^-1 X_{j+1}``), rotation trusted to a
  degree and translation to a tenth of the median step: the odometry's relative pose is the prior that
  holds a frame with few or no features (a sky, a wall, a textureless stretch) in place, and that keeps
  the ride's scale, which the bearings alone cannot see;
- one per observation: the bearing of the point from the frame (:class:`gtsam.BearingFactor3D`, an error
  of two angles), with the keypoints' noise as its standard deviation and a Huber kernel, so that a wrong
  match costs little once it disagrees with the rest.

The points start triangulated from the odometry's poses (:func:`triangulate`). After solving,
observations more than :attr:`BundleSettings.outlier` standard deviations off are dropped, the points
triangulated again from the solved poses, and the problem solved again (:attr:`BundleSettings.rounds`).

Why GTSAM and not COLMAP's bundle adjuster (pycolmap, with its EQUIRECTANGULAR camera): on the same
synthetic rides (``experiments/bundle_solvers.py``, docs/results/bundle-adjustment.md) both reach the same
step errors at 150 frames, GTSAM in half the time; at 600 frames they take the same time, and COLMAP's
step error is twice GTSAM's, its scale drifting. Only GTSAM takes the odometry's *relative* poses as
priors, which keep the ride's scale and hold the frames without features (COLMAP's pose priors are
absolute positions).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ...geometry import invert

__all__ = ["Adjusted", "BundleSettings", "Observations", "bundle_adjust", "triangulate"]


@dataclass(frozen=True)
class BundleSettings:
    """How the adjustment weighs and trims its measurements.

    Attributes:
        pixel_sigma: the keypoints' noise in pixels (a bearing's standard deviation is this times the
            angle of a pixel).
        huber: the Huber kernel's threshold on a bearing's error, in standard deviations.
        outlier: after a round, an observation farther off than this many standard deviations is dropped.
        step_rotation_deg: the odometry step prior's rotation (standard deviation, degrees).
        step_translation: its translation, as a fraction of the median step length.
        min_views: a point needs at least this many observations (after trimming) to be kept.
        min_parallax_deg: and rays at least this far apart (a point seen along one line has no depth).
        rounds: solve, trim the outliers, triangulate again, solve again: this many solves at most.
        iterations: Levenberg-Marquardt iterations per solve at most.
    """

    pixel_sigma: float = 0.3
    huber: float = 2.0
    outlier: float = 4.0
    step_rotation_deg: float = 1.0
    step_translation: float = 0.1
    min_views: int = 2
    min_parallax_deg: float = 1.0
    rounds: int = 2
    iterations: int = 10

    def __post_init__(self) -> None:
        positive = (self.pixel_sigma, self.huber, self.outlier, self.step_rotation_deg, self.step_translation)
        if not all(math.isfinite(v) and v > 0 for v in positive):
            raise InputError(
                "bundle: pixel_sigma, huber, outlier, step_rotation_deg and step_translation must be "
                f"positive, got {positive}"
            )
        if self.min_views < 2 or self.rounds < 1 or self.iterations < 1:
            raise InputError(
                f"bundle: min_views must be at least 2, rounds and iterations at least 1; got "
                f"{self.min_views}, {self.rounds}, {self.iterations}"
            )


@dataclass(frozen=True)
class Observations:
    """Which frame sees which point in which direction.

    Attributes:
        frame: ``[N]`` the observing frame (index into the ride).
        point: ``[N]`` the point (track) seen, ``0 .. P-1``.
        bearing: ``[N,3]`` unit bearings in the frame's camera axes (x right, y down, z forward).
        keypoint: ``[N]`` which keypoint of the ride each is (an index into every frame's keypoints in
            order), when it came from keypoints; else ``None``.
    """

    frame: np.ndarray
    point: np.ndarray
    bearing: np.ndarray
    keypoint: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.frame)
        if self.point.shape != (n,) or self.bearing.shape != (n, 3) or self.frame.shape != (n,):
            raise InputError(
                f"observations: frame [N], point [N] and bearing [N,3] must agree, got "
                f"{self.frame.shape}, {self.point.shape}, {self.bearing.shape}"
            )

    @property
    def points(self) -> int:
        """The number of points ``P`` (one more than the largest index)."""
        return int(self.point.max()) + 1 if len(self.point) else 0

    def subset(self, keep: np.ndarray) -> Observations:
        """The observations where ``keep [N]`` (bool) is true."""
        keypoint = None if self.keypoint is None else self.keypoint[keep]
        return Observations(self.frame[keep], self.point[keep], self.bearing[keep], keypoint)


@dataclass
class Adjusted:
    """The adjusted ride.

    Attributes:
        c2w: camera-to-world poses ``[M,4,4]``, in the odometry's scale.
        points: ``[P,3]`` world points (``nan`` where a point was not kept).
        inliers: ``[N]`` whether each observation was kept to the end.
        rounds: solves run.
        seconds: wall time.
    """

    c2w: np.ndarray
    points: np.ndarray
    inliers: np.ndarray
    rounds: int
    seconds: float


def triangulate(
    c2w: np.ndarray, obs: Observations, n_points: int, min_views: int = 2, min_parallax_deg: float = 1.0
) -> np.ndarray:
    """Each point ``[P,3]`` (``nan``: not kept) as the least-squares meeting of its rays from the frames'
    centres ``c2w [M,4,4]``: kept with at least ``min_views`` rays, ``min_parallax_deg`` between the most
    separated ray and the first, and in front of every camera that sees it."""
    rays = np.einsum("nij,nj->ni", c2w[obs.frame, :3, :3], obs.bearing)  # world directions [N,3]
    centres = c2w[obs.frame, :3, 3]
    proj = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]  # I - d d^T
    a = np.zeros((n_points, 3, 3))
    b = np.zeros((n_points, 3))
    np.add.at(a, obs.point, proj)
    np.add.at(b, obs.point, np.einsum("nij,nj->ni", proj, centres))
    views = np.bincount(obs.point, minlength=n_points)
    first = np.full((n_points, 3), np.nan)
    order = np.argsort(obs.point, kind="stable")
    starts = np.searchsorted(obs.point[order], np.arange(n_points))
    has = views > 0
    first[has] = rays[order[starts[has]]]
    cos = np.einsum("ni,ni->n", rays, first[obs.point])
    widest = np.full(n_points, 1.0)
    np.minimum.at(widest, obs.point, cos)
    ok = (views >= min_views) & (widest <= math.cos(math.radians(min_parallax_deg)))
    points = np.full((n_points, 3), np.nan)
    if ok.any():
        points[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    ahead = np.einsum("ni,ni->n", points[obs.point] - centres, rays) > 0
    behind = np.zeros(n_points, dtype=bool)
    np.logical_or.at(behind, obs.point, ~ahead & ok[obs.point])
    points[behind] = np.nan
    return points


def bundle_adjust(
    c2w: np.ndarray, obs: Observations, pixel_angle: float, settings: BundleSettings | None = None
) -> Adjusted:
    """Adjust the ride's poses ``c2w [M,4,4]`` (the odometry's: the seed and the step priors) and its points
    to the observations (see the module docstring).

    Args:
        c2w: the odometry's camera-to-world poses.
        obs: the observations (bearings).
        pixel_angle: the angle of one pixel of the frames (radians; ``1 / fx`` for a cylinder or an
            equirectangular panorama).
        settings: how to weigh and trim.

    Returns:
        :class:`Adjusted`; a ride with no point that can be triangulated keeps the odometry's poses.
    """
    import gtsam

    cfg = settings or BundleSettings()
    started = time.perf_counter()
    c2w = np.asarray(c2w, dtype=np.float64)
    n_points = obs.points
    keep = np.ones(len(obs.frame), dtype=bool)
    poses, points, rounds = c2w, np.full((n_points, 3), np.nan), 0
    sigma = cfg.pixel_sigma * pixel_angle
    for _ in range(cfg.rounds):
        points = triangulate(poses, obs.subset(keep), n_points, cfg.min_views, cfg.min_parallax_deg)
        used = keep & np.isfinite(points[obs.point, 0])
        if not used.any():
            break
        poses, points = _solve(gtsam, c2w, poses, points, obs.subset(used), sigma, cfg)
        rounds += 1
        err = _angles(poses, points, obs) / sigma
        trimmed = used & (err <= cfg.outlier)
        if np.array_equal(trimmed, keep):
            break
        keep = trimmed
    points = points.copy()
    views = np.bincount(obs.point[keep], minlength=n_points)
    points[views < cfg.min_views] = np.nan
    keep &= np.isfinite(points[obs.point, 0])
    return Adjusted(poses, points, keep, rounds, time.perf_counter() - started)


def _angles(c2w: np.ndarray, points: np.ndarray, obs: Observations) -> np.ndarray:
    """The angle (radians) between each observed bearing and the direction to its point (``inf`` where the
    point is not kept)."""
    local = np.einsum(
        "nji,nj->ni", c2w[obs.frame, :3, :3], points[obs.point] - c2w[obs.frame, :3, 3]
    )  # R^T (X - c)
    norm = np.linalg.norm(local, axis=1)
    cos = np.einsum("ni,ni->n", local, obs.bearing) / np.where(norm > 0, norm, 1.0)
    out = np.arccos(np.clip(cos, -1.0, 1.0))
    return np.where(np.isfinite(out), out, np.inf)


def _solve(gtsam, odometry, start, points, obs, sigma, cfg) -> tuple[np.ndarray, np.ndarray]:
    """One Levenberg-Marquardt solve from poses ``start`` and ``points`` (only the points observed)."""
    m = len(odometry)
    x, p = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for j in range(m):
        values.insert(x(j), gtsam.Pose3(start[j]))
    seen = np.unique(obs.point)
    for q in seen:
        values.insert(p(int(q)), points[q])
    graph.add(
        gtsam.PriorFactorPose3(x(0), gtsam.Pose3(odometry[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-9))
    )
    steps = [invert(odometry[j]) @ odometry[j + 1] for j in range(m - 1)]
    unit = float(np.median([np.linalg.norm(s[:3, 3]) for s in steps])) if steps else 1.0
    prior = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([math.radians(cfg.step_rotation_deg)] * 3 + [cfg.step_translation * (unit or 1.0)] * 3)
    )
    for j, step in enumerate(steps):
        graph.add(gtsam.BetweenFactorPose3(x(j), x(j + 1), gtsam.Pose3(step), prior))
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber), gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    )
    for j, q, b in zip(obs.frame.tolist(), obs.point.tolist(), obs.bearing, strict=True):
        graph.add(gtsam.BearingFactor3D(x(j), p(q), gtsam.Unit3(b), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    poses = np.stack([result.atPose3(x(j)).matrix() for j in range(m)])
    out = np.full_like(points, np.nan)
    for q in seen:
        out[q] = result.atPoint3(p(int(q)))
    return poses, out
