"""The ride: the camera's route through the town, like a cyclist's helmet camera.

About ``cfg.speed`` metres a frame with smooth speed changes and occasional stops, turns at the
intersections, on the right side of the streets between the traffic and the parked cars, with a little
pitch, roll and yaw wobble and a slightly varying height.
"""

from __future__ import annotations

import numpy as np

from ...geometry.pose import rotation_x, rotation_y, rotation_z
from .config import SynthConfig

__all__ = ["route_poses", "smooth_noise"]

_STEPS = [(1, 0), (0, 1), (-1, 0), (0, -1)]  # unit steps in the street grid (i -> x, j -> z)


def route_poses(rng: np.random.Generator, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [F,4,4] (``F = cfg.frames``) of a cyclist riding on the right side of the
    streets whose centre lines are ``xs`` (streets along z) and ``zs`` (streets along x)."""
    path, stops = _centre_line(rng, cfg, xs, zs)
    # Smooth the corners away (a Gaussian of about 4 m over arc length).
    k = np.arange(-12, 13)
    g = np.exp(-0.5 * (k / 4.0) ** 2)
    g /= g.sum()
    padded = np.concatenate([np.repeat(path[:1], 12, 0), path, np.repeat(path[-1:], 12, 0)])
    smooth = np.stack([np.convolve(padded[:, c], g, mode="valid") for c in range(2)], 1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(smooth, axis=0), axis=1))])

    f = cfg.frames
    s = _arc_positions(rng, cfg, stops, arc[-1])
    x = np.interp(s, arc, smooth[:, 0])
    z = np.interp(s, arc, smooth[:, 1])
    ahead = np.minimum(s + 2.0, arc[-1])
    behind = np.maximum(s - 2.0, 0.0)
    hx = np.interp(ahead, arc, smooth[:, 0]) - np.interp(behind, arc, smooth[:, 0])
    hz = np.interp(ahead, arc, smooth[:, 1]) - np.interp(behind, arc, smooth[:, 1])
    yaw = np.unwrap(np.arctan2(hx, hz)) + np.radians(cfg.yaw_wobble_deg) * smooth_noise(rng, f, 12.0)
    pitch = np.radians(cfg.jitter_deg) * (0.8 * smooth_noise(rng, f, 15.0) + 0.2 * smooth_noise(rng, f, 2.5))
    roll = np.radians(cfg.jitter_deg) * (0.8 * smooth_noise(rng, f, 18.0) + 0.2 * smooth_noise(rng, f, 3.0))
    height = cfg.camera_height + 0.03 * smooth_noise(rng, f, 4.0)
    c2w = np.zeros((f, 4, 4))
    c2w[:, :3, :3] = rotation_y(yaw) @ rotation_x(pitch) @ rotation_z(roll)
    c2w[:, 0, 3] = x
    c2w[:, 1, 3] = -height
    c2w[:, 2, 3] = z
    c2w[:, 3, 3] = 1
    return c2w


def _centre_line(
    rng: np.random.Generator, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray
) -> tuple[np.ndarray, list[float]]:
    """A random walk along the street grid: waypoints [N,2] (x, z) 1 m apart in the riding lane, and the
    arc-length positions (metres) where the cyclist stops."""
    n = len(xs)
    i, j = int(rng.integers(1, n - 1)), int(rng.integers(1, n - 1))
    d = int(rng.integers(4))
    lane = cfg.road_half_width - 3.0  # metres right of the centre line: between traffic and parked cars
    pts = []  # dense centre-line waypoints, 1 m apart, offset to the right
    stops = []  # arc-length positions where the cyclist stops
    length = 0.0
    need = cfg.frames * cfg.speed * 1.5 + 60
    while length < need:
        di, dj = _STEPS[d]
        ni, nj = i + di, j + dj
        if not (0 <= ni < n and 0 <= nj < n):
            d = (d + 2) % 4
            continue
        a = np.array([xs[i], zs[j]])
        b = np.array([xs[ni], zs[nj]])
        seg = np.linalg.norm(b - a)
        heading = (b - a) / seg
        right = np.array([heading[1], -heading[0]])  # x right of the heading (world x east, z north)
        for s in np.arange(0, seg, 1.0):
            pts.append(a + heading * s + right * lane)
        length += seg
        if rng.random() < cfg.stop_probability:
            stops.append(length - 10.0)
        i, j = ni, nj
        options = [d, (d + 1) % 4, (d + 3) % 4]
        weights = np.array([0.5, 0.25, 0.25])
        ok = [0 <= i + _STEPS[o][0] < n and 0 <= j + _STEPS[o][1] < n for o in options]
        weights = weights * np.array(ok, float)
        d = options[int(rng.choice(3, p=weights / weights.sum()))] if weights.sum() > 0 else (d + 2) % 4
    return np.array(pts), stops


def _arc_positions(rng: np.random.Generator, cfg: SynthConfig, stops: list[float], end: float) -> np.ndarray:
    """Arc-length position (metres) of the camera in each frame: float64 [F], smooth speed changes, a hold
    of 3 to 8 frames at each stop, never beyond ``end``."""
    f = cfg.frames
    speed = cfg.speed * (1 + cfg.speed_variation * smooth_noise(rng, f, 25.0))
    speed = np.maximum(speed, 0.2 * cfg.speed)
    s = np.concatenate([[0.0], np.cumsum(speed[:-1])]) + 5.0
    for stop in stops:  # hold still for a few frames when passing a stop point
        hit = np.nonzero(s >= stop)[0]
        if len(hit):
            k0 = hit[0]
            hold = int(rng.integers(3, 9))
            s = np.concatenate([s[:k0], np.full(hold, s[k0]), s[k0:]])[:f]
    return np.minimum(s, end - 1e-6)


def smooth_noise(rng: np.random.Generator, n: int, period: float) -> np.ndarray:
    """Smooth random signal [n] in about [-1, 1]: a sum of a few sinusoids with periods around ``period``
    frames."""
    t = np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for _ in range(3):
        p = period * rng.uniform(0.6, 1.6)
        out += np.sin(2 * np.pi * t / p + rng.uniform(0, 2 * np.pi)) / 3
    return out * 1.4
