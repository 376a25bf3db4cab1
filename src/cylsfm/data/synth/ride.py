"""The ride: the camera's route through the town, like a cyclist's helmet camera.

About ``cfg.speed`` metres a frame with smooth speed changes and occasional stops, turns at the
intersections, on the right side of the streets between the traffic and the parked cars, with a little
pitch, roll and yaw wobble and a slightly varying height.

The route (``cfg.route``) is a random walk along the street grid, or one of the rides that come back to
where they were (for loop closure): once around a block, a figure eight around two blocks, out and back
along the same streets (the return in the opposite direction, on the other side of the road); or a
staircase of alternating left and right turns that never passes a place twice. Those routes are built from
the street grid's intersections and fitted to the ride: the one whose length is nearest to
``cfg.frames * cfg.speed`` is taken and ridden at the speed that covers it in the ride's frames.
"""

from __future__ import annotations

import itertools

import numpy as np

from ...errors import InputError
from ...geometry.pose import rotation_x, rotation_y, rotation_z
from .config import SynthConfig

__all__ = ["ROUTES", "route_poses", "smooth_noise"]

#: The routes of :attr:`SynthConfig.route`.
ROUTES = ("random", "block", "eight", "back", "stairs")
#: Closed routes end where they start.
CLOSED = ("block", "eight")

_STEPS = [(1, 0), (0, 1), (-1, 0), (0, -1)]  # unit steps in the street grid (i -> x, j -> z)


def route_poses(rng: np.random.Generator, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [F,4,4] (``F = cfg.frames``) of a cyclist riding on the right side of the
    streets whose centre lines are ``xs`` (streets along z) and ``zs`` (streets along x)."""
    closed = cfg.route in CLOSED
    if cfg.route == "random":
        path, stops = _centre_line(rng, cfg, xs, zs)
    else:
        path, stops = _grid_route(rng, cfg, xs, zs), []
    # Smooth the corners away (a Gaussian of about 4 m over arc length; around a closed route, circularly).
    k = np.arange(-12, 13)
    g = np.exp(-0.5 * (k / 4.0) ** 2)
    g /= g.sum()
    if closed:
        padded = np.concatenate([path[-12:], path, path[:13]])  # the start point repeated at the end
    else:
        padded = np.concatenate([np.repeat(path[:1], 12, 0), path, np.repeat(path[-1:], 12, 0)])
    smooth = np.stack([np.convolve(padded[:, c], g, mode="valid") for c in range(2)], 1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(smooth, axis=0), axis=1))])

    f = cfg.frames
    if cfg.route == "random":
        s = _arc_positions(rng, cfg, stops, arc[-1])
    else:  # the whole route in the ride's frames (a closed one back at its start)
        s = _arc_positions(rng, cfg, stops, np.inf)
        first, last = (0.0, arc[-1]) if closed else (5.0, arc[-1] - 5.0)
        s = first + (s - s[0]) * ((last - first) / (s[-1] - s[0]))
    x = np.interp(s, arc, smooth[:, 0])
    z = np.interp(s, arc, smooth[:, 1])
    if closed:  # the heading looks across the start of a closed route
        ahead, behind = np.mod(s + 2.0, arc[-1]), np.mod(s - 2.0, arc[-1])
    else:
        ahead, behind = np.minimum(s + 2.0, arc[-1]), np.maximum(s - 2.0, 0.0)
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


def _grid_route(rng: np.random.Generator, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """The waypoints [N,2] (x, z), 1 m apart in the riding lane, of a route other than "random": of the
    candidate routes through the town's intersections, the one nearest in length to the ride's."""
    n = len(xs)
    if n < 4:
        raise InputError(f"route {cfg.route!r} needs a town of at least 3 x 3 blocks, this one has {n - 1}")
    lane = cfg.road_half_width - 3.0
    want = cfg.frames * cfg.speed
    options = []
    for nodes in _route_nodes(rng, cfg.route, n):
        pts = _lane_points(nodes, xs, zs, lane, closed=cfg.route in CLOSED)
        options.append((abs(len(pts) - want), pts))
    best = min(options, key=lambda o: o[0])[1]
    if not 0.75 * want <= len(best) <= 1.35 * want:
        raise InputError(
            f"route {cfg.route!r}: no such route in this town is about {want:.0f} m long (the nearest is "
            f"{len(best)} m): give about {len(best) / cfg.speed:.0f} frames"
        )
    return best


def _route_nodes(rng: np.random.Generator, route: str, n: int) -> list[list[tuple[int, int]]]:
    """Candidate routes as lists of grid intersections ``(i, j)`` (``xs[i], zs[j]``), each step to a
    neighbour; a closed route's last node is its first. Shuffled by the seed (ties in length)."""
    if route not in _NODES:
        raise InputError(f"route must be one of {', '.join(ROUTES)}, got {route!r}")
    out = _NODES[route](n)
    order = rng.permutation(len(out))
    return [out[k] for k in order]


def _blocks(n: int) -> list[list[tuple[int, int]]]:
    """Around block (i, j), counter-clockwise seen from above (x east, z north)."""
    return [
        [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1), (i, j)] for i in range(n - 1) for j in range(n - 1)
    ]


def _eights(n: int) -> list[list[tuple[int, int]]]:
    """Around block (i, j) and then (i+1, j): the street between them twice, northwards both times."""
    out = []
    for i in range(n - 2):
        for j in range(n - 1):
            a, b, c = i, i + 1, i + 2  # the columns of streets: west, middle, east
            out.append(
                [(b, j), (b, j + 1), (a, j + 1), (a, j), (b, j), (b, j + 1), (c, j + 1), (c, j), (b, j)]
            )
    return out


def _backs(n: int) -> list[list[tuple[int, int]]]:
    """East along street j from a to b, around the block north of its last stretch, back west to a."""
    out = []
    for j in range(n - 1):
        for a in range(n - 1):
            for b in range(a + 2, n):
                there = [(i, j) for i in range(a, b + 1)]
                back = [(i, j) for i in range(b - 2, a - 1, -1)]
                out.append([*there, (b, j + 1), (b - 1, j + 1), (b - 1, j), *back])
    return out


def _stairs(n: int) -> list[list[tuple[int, int]]]:
    """Alternately one block east and one block north (only one way when an edge is reached)."""
    out = []
    for i0 in range(n - 1):
        for j0 in range(n - 1):
            nodes, i, j = [(i0, j0)], i0, j0
            while i + 1 < n or j + 1 < n:
                if i + 1 < n and (len(nodes) % 2 == 1 or j + 1 >= n):
                    i += 1
                else:
                    j += 1
                nodes.append((i, j))
                if len(nodes) > 2:
                    out.append(list(nodes))
    return out


_NODES = {"block": _blocks, "eight": _eights, "back": _backs, "stairs": _stairs}


def _lane_points(
    nodes: list[tuple[int, int]], xs: np.ndarray, zs: np.ndarray, lane: float, closed: bool
) -> np.ndarray:
    """Points 1 m apart along the segments between ``nodes``, ``lane`` metres right of the centre line;
    a closed route starts half way along its first segment (away from the corners)."""
    pts = []
    for (i, j), (ni, nj) in itertools.pairwise(nodes):
        a, b = np.array([xs[i], zs[j]]), np.array([xs[ni], zs[nj]])
        seg = float(np.linalg.norm(b - a))
        heading = (b - a) / seg
        right = np.array([heading[1], -heading[0]])
        for s in np.arange(0, seg, 1.0):
            pts.append(a + heading * s + right * lane)
    if not closed:
        pts.append(b + right * lane)
    out = np.array(pts)
    if closed:
        first = int(
            np.linalg.norm(
                np.array([xs[nodes[1][0]], zs[nodes[1][1]]]) - np.array([xs[nodes[0][0]], zs[nodes[0][1]]])
            )
        )
        out = np.roll(out, -(first // 2), axis=0)
    return out


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
