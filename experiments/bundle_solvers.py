"""Which solver for the bundle adjustment of a ride: the project's (GTSAM, bearings and the odometry's
steps as priors, :func:`cylsfm.odometry.bundle.bundle_adjust`) against COLMAP's bundle adjuster (pycolmap,
one EQUIRECTANGULAR camera, a Cauchy loss, the first frame fixed), on the same synthetic problem.

Usage::

    python experiments/bundle_solvers.py [FRAMES ...]     # default: 150 600

The problem: a gently curving ride of FRAMES panoramas a metre apart, 60 points beside the road per frame
(3-8 m to the side, -1.5 to 2.5 m high), each seen by the 7 frames around it, bearings with 0.5 pixel of
noise at 512 pixels a turn; the odometry's steps off by 3% in length and 0.17 degrees in yaw each. Printed
per solver: seconds to build the problem and to solve it, and the mean error of a step's translation (m,
the estimate brought to the truth's scale by the ride's length, since neither sees the scale) and
rotation (degrees), and the largest position error.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from cylsfm.geometry import invert, rotation_y
from cylsfm.odometry.bundle import BundleSettings, Observations, bundle_adjust, triangulate

WIDTH = 512  # pixels a turn
NOISE = 0.5  # pixels


def ride(m: int, rng: np.random.Generator):
    yaw = np.cumsum(np.r_[0.0, rng.normal(0, 0.02, m - 1)])
    c2w = np.tile(np.eye(4), (m, 1, 1))
    for j in range(m):
        c2w[j, :3, :3] = rotation_y(np.asarray(yaw[j]))
        if j:
            c2w[j, :3, 3] = c2w[j - 1, :3, 3] + c2w[j, :3, :3] @ np.array([0.0, 0.0, 1.0])
    n = 60 * m
    local = np.stack(
        [rng.choice([-1.0, 1.0], n) * rng.uniform(3, 8, n), rng.uniform(-1.5, 2.5, n), rng.uniform(-2, 2, n)],
        1,
    )
    home = np.repeat(np.arange(m), 60)
    points = np.einsum("nij,nj->ni", c2w[home, :3, :3], local) + c2w[home, :3, 3]
    frame = np.concatenate([np.arange(max(0, j - 3), min(m, j + 4)) for j in home])
    point = np.concatenate([np.full(min(m, j + 4) - max(0, j - 3), q) for q, j in enumerate(home)])
    rel = np.einsum("nji,nj->ni", c2w[frame, :3, :3], points[point] - c2w[frame, :3, 3])
    bearing = rel / np.linalg.norm(rel, axis=1, keepdims=True)
    noise = rng.normal(0, NOISE * 2 * math.pi / WIDTH, bearing.shape)
    noise -= bearing * np.einsum("ni,ni->n", noise, bearing)[:, None]
    bearing = bearing + noise
    bearing /= np.linalg.norm(bearing, axis=1, keepdims=True)
    odometry = c2w.copy()
    for j in range(m - 1):
        step = invert(c2w[j]) @ c2w[j + 1]
        step[:3, 3] *= 1 + rng.normal(0, 0.03)
        step[:3, :3] = rotation_y(np.asarray(rng.normal(0, 0.003))) @ step[:3, :3]
        odometry[j + 1] = odometry[j] @ step
    return c2w, odometry, Observations(frame, point, bearing)


def errors(est: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    def length(c):
        return np.linalg.norm(np.diff(c[:, :3, 3], axis=0), axis=1).sum()

    est = est.copy()
    est[:, :3, 3] = (est[:, :3, 3] - est[0, :3, 3]) * (length(truth) / length(est)) + est[0, :3, 3]
    trans, rot = [], []
    for j in range(len(truth) - 1):
        a, b = invert(est[j]) @ est[j + 1], invert(truth[j]) @ truth[j + 1]
        trans.append(np.linalg.norm(a[:3, 3] - b[:3, 3]))
        rot.append(math.degrees(math.acos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1))))
    return float(np.mean(trans)), float(np.mean(rot)), float(np.abs(est[:, :3, 3] - truth[:, :3, 3]).max())


def colmap(odometry: np.ndarray, obs: Observations) -> tuple[np.ndarray, float, float]:
    import pycolmap as pc

    t0 = time.perf_counter()
    m, height = len(odometry), WIDTH // 2
    points = triangulate(odometry, obs, obs.points)
    rec = pc.Reconstruction()
    cam = pc.Camera(camera_id=1, model="EQUIRECTANGULAR", width=WIDTH, height=height, params=[WIDTH, height])
    rec.add_camera(cam)
    rig = pc.Rig(rig_id=1)
    rig.add_ref_sensor(pc.sensor_t(type=pc.SensorType.CAMERA, id=1))
    rec.add_rig(rig)
    keypoints = [[] for _ in range(m)]
    tracks = [pc.Track() for _ in range(obs.points)]
    for j, q, xy in zip(
        obs.frame, obs.point, cam.img_from_cam(obs.bearing, check_cheirality=False), strict=True
    ):
        if np.isfinite(points[q, 0]):
            tracks[q].add_element(int(j) + 1, len(keypoints[j]))
            keypoints[j].append(xy)
    for j in range(m):
        frame = pc.Frame(frame_id=j + 1, rig_id=1, rig_from_world=pc.Rigid3d(invert(odometry[j])[:3]))
        frame.add_data_id(pc.data_t(sensor_id=pc.sensor_t(type=pc.SensorType.CAMERA, id=1), id=j + 1))
        rec.add_frame(frame)
        image = pc.Image(image_id=j + 1, name=str(j), camera_id=1, frame_id=j + 1)
        image.points2D = pc.Point2DList([pc.Point2D(xy) for xy in keypoints[j]])
        rec.add_image(image)
    for q in range(obs.points):
        if np.isfinite(points[q, 0]):
            rec.add_point3D(points[q], tracks[q], np.zeros(3, np.uint8))
    t1 = time.perf_counter()
    options = pc.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_extra_params = options.print_summary = False
    options.ceres.loss_function_type = pc.LossFunctionType.CAUCHY
    config = pc.BundleAdjustmentConfig()
    for j in range(m):
        config.add_image(j + 1)
    config.set_constant_cam_intrinsics(1)
    config.set_constant_rig_from_world_pose(1)
    pc.create_default_bundle_adjuster(options, config, rec).solve()
    t2 = time.perf_counter()
    est = np.stack(
        [invert(np.vstack([rec.frames[j + 1].rig_from_world.matrix(), [0, 0, 0, 1]])) for j in range(m)]
    )
    return est, t1 - t0, t2 - t1


def main(sizes: list[int]) -> None:
    for m in sizes:
        truth, odometry, obs = ride(m, np.random.default_rng(0))
        print(f"{m} frames, {obs.points} points, {len(obs.frame)} observations")
        line = "step {:.4f} m {:.4f} deg, largest position error {:.3f} m"
        print(f"  odometry                              {line.format(*errors(odometry, truth))}")
        done = bundle_adjust(odometry, obs, 2 * math.pi / WIDTH, BundleSettings(pixel_sigma=NOISE, rounds=1))
        print(f"  gtsam (bearings)    {done.seconds:6.2f} s          {line.format(*errors(done.c2w, truth))}")
        est, build, solve = colmap(odometry, obs)
        print(f"  pycolmap (equirect) {build:6.2f} s + {solve:5.2f} s {line.format(*errors(est, truth))}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [150, 600])
