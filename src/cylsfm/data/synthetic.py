"""Procedural 360-degree street scenes with exact ground truth: the built-in benchmark of cylsfm.

A town is a grid of streets (asphalt with lane markings, sidewalks with paving) and blocks of buildings
(boxes of varied size and height with window grids and brick, plaster or concrete facades), with parked
cars, street lamps and trees, optionally cars driving along the lanes, under a sky at infinity. A camera
rides through it like a cyclist's helmet camera: about one metre per frame with smooth speed changes and
occasional stops, turns at intersections, a little pitch, roll and yaw wobble.

Frames are ray cast directly in the target projection (cylindrical, equirectangular or pinhole), anti-aliased
by supersampling, with the true depth of every pixel (the projection's depth; 0 for sky) and the true
camera-to-world pose of every frame. Everything is a vertical prism (boxes and cylinders standing on the
ground), so each ray only has to be tested against the objects whose horizontal footprint lies in its
azimuth: an azimuth-binned candidate list keeps the cost near linear in the number of pixels.

Textures are evaluated at the world point that a ray hits (periodic noise tiles sampled bilinearly, plus
procedural windows, bricks, paving and markings), so every surface carries photometric detail. Shading is
a sun plus ambient light. A scene is a pure function of its seed: the same seed gives the same town,
route, images and ground truth.

World frame: x east, y down (gravity), z north; the ground is the plane y = 0.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..geometry import Camera, CylindricalCamera, EquirectangularCamera, PinholeCamera

__all__ = ["StreetScene", "SynthConfig", "generate_dataset", "make_camera", "render_frame"]

BOX, CYLINDER = 0, 1
# materials
FACADE, ROOF, CAR_BODY, CAR_GLASS, CAR_UNDER, POLE, TRUNK, CROWN = range(8)
_SUN = np.array([0.45, -0.8, 0.4]) / np.linalg.norm([0.45, -0.8, 0.4])  # towards the sun (y is down)
_MAX_RANGE = 160.0
_TILE = 256


# ----------------------------------------------------------------------------- configuration
@dataclass
class SynthConfig:
    """Parameters of a generated town and ride (all lengths in metres, per frame at ``fps``)."""

    frames: int = 200
    speed: float = 1.0  # mean distance per frame
    speed_variation: float = 0.25  # relative amplitude of the smooth speed changes
    stop_probability: float = 0.15  # chance of a short stop at an intersection
    camera_height: float = 1.75
    jitter_deg: float = 2.5  # amplitude of pitch and roll wobble
    yaw_wobble_deg: float = 2.0
    fps: float = 5.0
    moving_cars: int = 0
    block_size: tuple[float, float] = (45.0, 90.0)
    road_half_width: float = 7.0
    sidewalk_width: float = 3.0
    building_height: tuple[float, float] = (5.0, 40.0)
    texture_filter: float = 1.0  # width, in pixels, of the box filter applied to textures (optical blur)
    supersample: int = 1  # 1: quincunx (5 samples, 2 rays a pixel); n >= 2: n x n rays a pixel


@dataclass
class _Prisms:
    """Struct of arrays of vertical prisms (boxes and cylinders standing between y_top and y_bot)."""

    kind: np.ndarray  # int8 [N]
    a: np.ndarray  # float64 [N, 4]: box x0, x1, z0, z1 | cylinder cx, cz, r, 0
    y_top: np.ndarray  # float64 [N] (negative: above the ground)
    y_bot: np.ndarray  # float64 [N]
    material: np.ndarray  # int8 [N]
    colour: np.ndarray  # float64 [N, 3]
    param: np.ndarray  # float64 [N, 4]: per-material parameters (facade: floor h, window pitch, style, seed)

    @staticmethod
    def concat(parts: list[_Prisms]) -> _Prisms:
        return _Prisms(*(np.concatenate([getattr(p, f) for p in parts]) for f in _PRISM_FIELDS))

    def __len__(self) -> int:
        return len(self.kind)


_PRISM_FIELDS = ("kind", "a", "y_top", "y_bot", "material", "colour", "param")


def _prisms(rows: list[tuple]) -> _Prisms:
    if not rows:
        return _Prisms(
            np.zeros(0, np.int8),
            np.zeros((0, 4)),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, np.int8),
            np.zeros((0, 3)),
            np.zeros((0, 4)),
        )
    kind, a, yt, yb, mat, col, par = zip(*rows, strict=True)
    return _Prisms(
        np.array(kind, np.int8),
        np.array(a, np.float64),
        np.array(yt, np.float64),
        np.array(yb, np.float64),
        np.array(mat, np.int8),
        np.array(col, np.float64),
        np.array(par, np.float64),
    )


# ----------------------------------------------------------------------------- textures
def _periodic_noise(rng: np.random.Generator, size: int, falloff: float) -> np.ndarray:
    """A periodic ``size x size`` noise tile in [0, 1] with a ``1/f^falloff`` spectrum (FFT-filtered)."""
    white = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    rad = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    rad[0, 0] = 1.0
    spec = np.fft.fft2(white) / rad**falloff
    spec[0, 0] = 0
    tile = np.real(np.fft.ifft2(spec))
    tile = (tile - tile.mean()) / (tile.std() + 1e-12)
    return np.clip(0.5 + 0.18 * tile, 0, 1).astype(np.float32)


class _Mip:
    """A periodic texture tile with its box-filtered mip levels, for footprint-aware (trilinear) lookups."""

    def __init__(self, tile: np.ndarray) -> None:
        levels = [tile.astype(np.float32)]
        while levels[-1].shape[0] > 1:
            t = levels[-1]
            levels.append(0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2]))
        self.sizes = np.array([lv.shape[0] for lv in levels], np.int32)
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes**2)[:-1]]).astype(np.int64)
        self.atlas = np.concatenate([lv.ravel() for lv in levels])
        self.top = len(levels) - 1

    def _bilinear(self, level: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        n = self.sizes[level]
        mask = n - 1
        x = x / (1 << level).astype(np.float32) - np.float32(0.5)
        y = y / (1 << level).astype(np.float32) - np.float32(0.5)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        ix, iy = x0.astype(np.int64) & mask, y0.astype(np.int64) & mask
        ix1, iy1 = (ix + 1) & mask, (iy + 1) & mask
        base = self.offsets[level]
        a = self.atlas
        top = a[base + iy * n + ix] * (1 - fx) + a[base + iy * n + ix1] * fx
        bot = a[base + iy1 * n + ix] * (1 - fx) + a[base + iy1 * n + ix1] * fx
        return top * (1 - fy) + bot * fy

    def sample(self, u: np.ndarray, v: np.ndarray, scale: float, footprint: np.ndarray) -> np.ndarray:
        """Texture at surface coordinates ``(u, v)`` (metres) at ``scale`` texels per metre, averaged over
        a footprint of ``footprint`` metres (the level of detail is ``log2`` of its size in texels)."""
        x = u * np.float32(scale)
        y = v * np.float32(scale)
        lod = np.clip(np.log2(np.maximum(footprint * np.float32(scale), np.float32(1))), 0, self.top - 1e-3)
        l0 = np.floor(lod).astype(np.int64)
        frac = (lod - l0).astype(np.float32)
        return self._bilinear(l0, x, y) * (1 - frac) + self._bilinear(l0 + 1, x, y) * frac


def _band(x: np.ndarray, lo: float | np.ndarray, hi: float | np.ndarray, fw: np.ndarray) -> np.ndarray:
    """Fraction of the window ``[x - fw/2, x + fw/2]`` inside ``[lo, hi]``: a box-filtered indicator."""
    h = np.float32(0.5) * fw
    return (np.clip(x + h, lo, hi) - np.clip(x - h, lo, hi)) / np.maximum(fw, np.float32(1e-6))


def _pulse(x: np.ndarray, period: float | np.ndarray, lo: float, hi: float, fw: np.ndarray) -> np.ndarray:
    """Box-filtered periodic pulse train: the fraction of ``[x - fw/2, x + fw/2]`` where
    ``frac(x / period)`` lies in ``[lo, hi]`` (analytic, so it never aliases)."""

    def integral(y):
        q = y / period
        n = np.floor(q)
        return (n * (hi - lo) + np.clip(q - n, lo, hi) - lo) * period

    fw = np.maximum(fw, np.float32(1e-6))
    h = np.float32(0.5) * fw
    return np.clip((integral(x + h) - integral(x - h)) / fw, 0, 1)


def _hash01(*ints: np.ndarray) -> np.ndarray:
    """Deterministic hash of integer arrays to [0, 1) (integer arithmetic only)."""
    h = np.uint64(0x9E3779B97F4A7C15)
    acc = np.zeros(np.broadcast(*ints).shape, np.uint64)
    for v in ints:
        acc = acc ^ (
            np.asarray(v).astype(np.int64).astype(np.uint64)
            + h
            + (acc << np.uint64(6))
            + (acc >> np.uint64(2))
        )
        acc = acc * np.uint64(0xBF58476D1CE4E5B9)
        acc = acc ^ (acc >> np.uint64(31))
    return (acc >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)


# ----------------------------------------------------------------------------- the scene
@dataclass
class StreetScene:
    """A town (streets, blocks, objects), its moving cars and the camera's route.

    Build one with :meth:`generate`; render frames with :func:`render_frame`.
    """

    seed: int
    config: SynthConfig
    xs: np.ndarray  # centre lines of the streets running along z (their x), sorted
    zs: np.ndarray  # centre lines of the streets running along x (their z), sorted
    static: _Prisms
    movers: list[dict] = field(
        default_factory=list
    )  # moving cars: axis, line, lane offset, start, speed, colour
    c2w: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # [F, 4, 4] camera-to-world
    tiles: dict[str, _Mip] = field(default_factory=dict)
    sky_tile: _Mip | None = None
    park_blocks: np.ndarray = field(default_factory=lambda: np.zeros((1, 1), bool))  # [i, j] block is a park

    # -------------------------------------------------------------- generation
    @classmethod
    def generate(cls, seed: int, config: SynthConfig | None = None) -> StreetScene:
        cfg = config or SynthConfig()
        rng = np.random.default_rng(seed)
        corridor = cfg.road_half_width + cfg.sidewalk_width
        n_blocks = int(np.clip(math.ceil(math.sqrt(cfg.frames * cfg.speed) / 3.5) + 3, 4, 14))
        gaps = rng.uniform(*cfg.block_size, size=(2, n_blocks)) + 2 * corridor
        xs = np.concatenate(([0.0], np.cumsum(gaps[0])))
        zs = np.concatenate(([0.0], np.cumsum(gaps[1])))
        xs -= xs.mean()
        zs -= zs.mean()
        tiles = {
            "asphalt": _Mip(_periodic_noise(rng, _TILE, 0.6)),
            "fine": _Mip(_periodic_noise(rng, _TILE, 0.3)),
            "coarse": _Mip(_periodic_noise(rng, _TILE, 1.4)),
            "leaves": _Mip(_periodic_noise(rng, _TILE, 0.2)),
        }
        sky_tile = _Mip(_periodic_noise(rng, _TILE, 1.6))
        park_blocks = rng.random((n_blocks, n_blocks)) < 0.08
        rows: list[tuple] = []
        for i in range(n_blocks):
            for j in range(n_blocks):
                bx0, bx1 = xs[i] + corridor, xs[i + 1] - corridor
                bz0, bz1 = zs[j] + corridor, zs[j + 1] - corridor
                if park_blocks[i, j]:
                    _park(rng, rows, bx0, bx1, bz0, bz1)
                else:
                    _block(rng, rows, cfg, bx0, bx1, bz0, bz1)
        _street_furniture(rng, rows, cfg, xs, zs)
        scene = cls(seed, cfg, xs, zs, _prisms(rows), tiles=tiles, sky_tile=sky_tile, park_blocks=park_blocks)
        scene.c2w = _route(rng, cfg, xs, zs)
        scene.movers = _movers(rng, cfg, xs, zs, scene.c2w)
        return scene

    # -------------------------------------------------------------- objects of a frame
    def prisms_at(self, frame: int) -> _Prisms:
        """Static objects plus the moving cars at their positions in ``frame``."""
        if not self.movers:
            return self.static
        rows: list[tuple] = []
        for m in self.movers:
            along = float(_mover_along(m, frame))
            if m["axis"] == "z":
                _car(rows, m["line"] + m["offset"], along, "z", m["colour"], m["id"])
            else:
                _car(rows, along, m["line"] + m["offset"], "x", m["colour"], m["id"])
        return _Prisms.concat([self.static, _prisms(rows)])


def _block(rng, rows, cfg: SynthConfig, x0: float, x1: float, z0: float, z1: float) -> None:
    """Buildings along the four sides of a block and a lower filler in its middle, none overlapping.

    (Overlapping boxes would show two coplanar facades whose winner flips between frames.) The two sides
    facing x-running streets take the full block width; the other two fill the space between them.
    """
    reach = {}  # how far the buildings of each side extend into the block
    for side in (0, 1, 2, 3):
        along_x = side in (0, 1)  # facades facing an x-running street (normal along z)
        if along_x:
            lo, hi = x0, x1
            max_depth = min(22.0, (z1 - z0) / 2 - 3.0)
        else:
            lo, hi = z0 + reach[0], z1 - reach[1]
            max_depth = min(22.0, (x1 - x0) / 2 - 3.0)
        reach[side] = 0.0
        pos = lo
        while pos < hi - 4 and max_depth > 4:
            width = min(rng.uniform(8, 26), hi - pos)
            setback = rng.uniform(0, 2.5) if rng.random() < 0.6 else 0.0
            depth = rng.uniform(min(10.0, max_depth), max_depth)
            height = float(np.clip(rng.lognormal(math.log(14), 0.55), *cfg.building_height))
            near_edge = (z0, z1, x0, x1)[side]
            sign = 1 if side in (0, 2) else -1
            span = sorted((near_edge + sign * setback, near_edge + sign * (setback + depth)))
            if along_x:
                box = (pos, pos + width, span[0], span[1])
            else:
                box = (span[0], span[1], pos, pos + width)
            rows.append((BOX, box, -height, 0.0, FACADE, _building_colour(rng), _facade(rng)))
            reach[side] = max(reach[side], setback + depth)
            pos += width + (rng.uniform(0.5, 5) if rng.random() < 0.3 else 0.0)
    # the middle of the block, seen only over lower buildings
    fx0, fx1, fz0, fz1 = x0 + reach[2], x1 - reach[3], z0 + reach[0], z1 - reach[1]
    if fx1 - fx0 > 4 and fz1 - fz0 > 4:
        h = float(rng.uniform(4, 12))
        rows.append((BOX, (fx0, fx1, fz0, fz1), -h, 0.0, FACADE, _building_colour(rng), _facade(rng)))


def _park(rng, rows, x0: float, x1: float, z0: float, z1: float) -> None:
    for _ in range(int((x1 - x0) * (z1 - z0) / 120)):
        _tree(rng, rows, rng.uniform(x0 + 2, x1 - 2), rng.uniform(z0 + 2, z1 - 2))


def _building_colour(rng) -> tuple[float, float, float]:
    palette = np.array(
        [
            [0.78, 0.70, 0.58],
            [0.62, 0.33, 0.25],
            [0.70, 0.70, 0.68],
            [0.88, 0.86, 0.80],
            [0.55, 0.52, 0.50],
            [0.80, 0.62, 0.45],
            [0.60, 0.66, 0.72],
            [0.85, 0.78, 0.62],
        ]
    )
    c = palette[rng.integers(len(palette))] * rng.uniform(0.8, 1.1) + rng.normal(0, 0.03, 3)
    return tuple(np.clip(c, 0.05, 0.95))


def _facade(rng) -> tuple[float, float, float, float]:
    """Per-building facade parameters: floor height, window pitch, style (0 plaster, 1 brick, 2 concrete), seed."""
    return (
        float(rng.uniform(2.8, 3.8)),
        float(rng.uniform(2.2, 4.0)),
        float(rng.integers(3)),
        float(rng.integers(1 << 30)),
    )


def _tree(rng, rows, x: float, z: float) -> None:
    r = float(rng.uniform(1.4, 2.6))
    trunk_h = float(rng.uniform(2.2, 3.2))
    crown_h = float(rng.uniform(3.0, 6.0))
    seed = float(rng.integers(1 << 30))
    green = tuple(
        np.clip(np.array([0.25, 0.45, 0.18]) * rng.uniform(0.7, 1.3) + rng.normal(0, 0.03, 3), 0, 1)
    )
    rows.append((CYLINDER, (x, z, 0.2, 0), -trunk_h - 0.5, 0.0, TRUNK, (0.35, 0.25, 0.17), (0, 0, 0, seed)))
    rows.append((CYLINDER, (x, z, r, 0), -trunk_h - crown_h, -trunk_h, CROWN, green, (0, 0, 0, seed)))


def _car(rows, x: float, z: float, axis: str, colour, seed: float) -> None:
    """A car centred at (x, z), its length along ``axis``: underbody, body and glass cabin."""

    def box(half_len, half_wid, yt, yb, mat, col):
        if axis == "z":
            a = (x - half_wid, x + half_wid, z - half_len, z + half_len)
        else:
            a = (x - half_len, x + half_len, z - half_wid, z + half_wid)
        rows.append((BOX, a, yt, yb, mat, col, (0, 0, 0, seed)))

    box(1.75, 0.82, -0.42, 0.0, CAR_UNDER, (0.05, 0.05, 0.05))
    box(2.15, 0.9, -1.0, -0.42, CAR_BODY, colour)
    box(1.2, 0.8, -1.45, -1.0, CAR_GLASS, (0.15, 0.18, 0.22))


def _car_colour(rng) -> tuple[float, float, float]:
    palette = np.array(
        [
            [0.7, 0.05, 0.05],
            [0.9, 0.9, 0.9],
            [0.1, 0.1, 0.1],
            [0.1, 0.2, 0.6],
            [0.6, 0.6, 0.62],
            [0.85, 0.7, 0.1],
            [0.2, 0.45, 0.3],
        ]
    )
    return tuple(np.clip(palette[rng.integers(len(palette))] + rng.normal(0, 0.04, 3), 0.02, 0.98))


def _street_furniture(rng, rows, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray) -> None:
    """Parked cars along the kerbs, lamps and trees along the sidewalks."""
    rw, sw = cfg.road_half_width, cfg.sidewalk_width
    corridor = rw + sw
    for axis, lines, cross in (("z", xs, zs), ("x", zs, xs)):
        for line in lines:
            for k in range(len(cross) - 1):
                lo, hi = cross[k] + corridor + 2, cross[k + 1] - corridor - 2
                for side in (-1, 1):
                    # parked cars in the kerb lane
                    pos = lo + rng.uniform(0, 4)
                    while pos < hi - 5:
                        if rng.random() < 0.45:
                            off = side * (rw - 1.1)
                            cx, cz = (line + off, pos + 2.2) if axis == "z" else (pos + 2.2, line + off)
                            _car(rows, cx, cz, axis, _car_colour(rng), float(rng.integers(1 << 30)))
                        pos += rng.uniform(5.2, 7.5)
                    # lamps and trees on the sidewalk
                    pos = lo + rng.uniform(0, 10)
                    while pos < hi:
                        off = side * (rw + 0.6)
                        cx, cz = (line + off, pos) if axis == "z" else (pos, line + off)
                        if rng.random() < 0.5:
                            rows.append(
                                (
                                    CYLINDER,
                                    (cx, cz, 0.12, 0),
                                    -float(rng.uniform(5, 7)),
                                    0.0,
                                    POLE,
                                    (0.3, 0.32, 0.33),
                                    (0, 0, 0, 0),
                                )
                            )
                        else:
                            off_t = side * (rw + sw * 0.55)
                            tx, tz = (line + off_t, pos) if axis == "z" else (pos, line + off_t)
                            _tree(rng, rows, tx, tz)
                        pos += rng.uniform(12, 28)


def _movers(rng, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray, c2w: np.ndarray) -> list[dict]:
    """Cars driving along the lanes at constant speeds, never through the camera (3.5 m clearance)."""
    out: list[dict] = []
    cam = c2w[:, [0, 2], 3]
    frames = np.arange(len(c2w))
    for n in range(cfg.moving_cars):
        for _ in range(50):
            axis = "z" if rng.random() < 0.5 else "x"
            lines, cross = (xs, zs) if axis == "z" else (zs, xs)
            line = float(lines[rng.integers(len(lines))])
            direction = 1 if rng.random() < 0.5 else -1
            mover = {
                "axis": axis,
                "line": line,
                # drive on the right: the lane centre is 2 m right of the centre line
                "offset": float(rng.uniform(1.8, 2.2)) * direction * (1 if axis == "z" else -1),
                "start": float(rng.uniform(cross[0], cross[-1])),
                "speed": direction * float(rng.uniform(0.8, 2.0)),
                "range": (float(cross[0]), float(cross[-1])),
                "colour": _car_colour(rng),
                "id": float(1_000_000 + n),
            }
            along = _mover_along(mover, frames)
            pos = np.stack([np.full_like(along, line + mover["offset"]), along], 1)
            if axis == "x":
                pos = pos[:, ::-1]
            if np.min(np.linalg.norm(pos - cam, axis=1)) > 3.5:
                out.append(mover)
                break
    return out


def _mover_along(m: dict, frame: np.ndarray | int) -> np.ndarray:
    """Position of a moving car along its street at ``frame`` (it wraps around the town)."""
    lo, hi = m["range"]
    return lo + (m["start"] + m["speed"] * np.asarray(frame, np.float64) - lo) % (hi - lo)


# ----------------------------------------------------------------------------- the ride
def _route(rng, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [F,4,4] of a cyclist riding on the right side of the streets."""
    n = len(xs)
    i, j = int(rng.integers(1, n - 1)), int(rng.integers(1, n - 1))
    dirs = [(1, 0), (0, 1), (-1, 0), (0, -1)]  # unit steps in (i -> x, j -> z)
    d = int(rng.integers(4))
    lane = cfg.road_half_width - 3.0  # metres right of the centre line: between traffic and parked cars
    pts = []  # dense centre-line waypoints, 1 m apart, offset to the right
    stops = []  # arc-length positions where the cyclist stops
    length = 0.0
    need = cfg.frames * cfg.speed * 1.5 + 60
    while length < need:
        di, dj = dirs[d]
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
        ok = [0 <= i + dirs[o][0] < n and 0 <= j + dirs[o][1] < n for o in options]
        weights = weights * np.array(ok, float)
        d = options[int(rng.choice(3, p=weights / weights.sum()))] if weights.sum() > 0 else (d + 2) % 4
    path = np.array(pts)
    # Smooth the corners away (a Gaussian of about 4 m over arc length).
    k = np.arange(-12, 13)
    g = np.exp(-0.5 * (k / 4.0) ** 2)
    g /= g.sum()
    padded = np.concatenate([np.repeat(path[:1], 12, 0), path, np.repeat(path[-1:], 12, 0)])
    smooth = np.stack([np.convolve(padded[:, c], g, mode="valid") for c in range(2)], 1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(smooth, axis=0), axis=1))])

    f = cfg.frames
    t = np.arange(f, dtype=np.float64)
    speed = cfg.speed * (1 + cfg.speed_variation * _smooth_noise(rng, f, 25.0))
    speed = np.maximum(speed, 0.2 * cfg.speed)
    s = np.concatenate([[0.0], np.cumsum(speed[:-1])]) + 5.0
    for stop in stops:  # hold still for a few frames when passing a stop point
        hit = np.nonzero(s >= stop)[0]
        if len(hit):
            k0 = hit[0]
            hold = int(rng.integers(3, 9))
            s = np.concatenate([s[:k0], np.full(hold, s[k0]), s[k0:]])[:f]
    s = np.minimum(s, arc[-1] - 1e-6)
    x = np.interp(s, arc, smooth[:, 0])
    z = np.interp(s, arc, smooth[:, 1])
    ahead = np.minimum(s + 2.0, arc[-1])
    behind = np.maximum(s - 2.0, 0.0)
    hx = np.interp(ahead, arc, smooth[:, 0]) - np.interp(behind, arc, smooth[:, 0])
    hz = np.interp(ahead, arc, smooth[:, 1]) - np.interp(behind, arc, smooth[:, 1])
    yaw = np.unwrap(np.arctan2(hx, hz)) + np.radians(cfg.yaw_wobble_deg) * _smooth_noise(rng, f, 12.0)
    pitch = np.radians(cfg.jitter_deg) * (
        0.8 * _smooth_noise(rng, f, 15.0) + 0.2 * _smooth_noise(rng, f, 2.5)
    )
    roll = np.radians(cfg.jitter_deg) * (0.8 * _smooth_noise(rng, f, 18.0) + 0.2 * _smooth_noise(rng, f, 3.0))
    height = cfg.camera_height + 0.03 * _smooth_noise(rng, f, 4.0)
    c2w = np.zeros((f, 4, 4))
    c2w[:, :3, :3] = _rot_y(yaw) @ _rot_x(pitch) @ _rot_z(roll)
    c2w[:, 0, 3] = x
    c2w[:, 1, 3] = -height
    c2w[:, 2, 3] = z
    c2w[:, 3, 3] = 1
    del t
    return c2w


def _smooth_noise(rng, n: int, period: float) -> np.ndarray:
    """Smooth random signal in about [-1, 1]: a sum of a few sinusoids with periods around ``period`` frames."""
    t = np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for _ in range(3):
        p = period * rng.uniform(0.6, 1.6)
        out += np.sin(2 * np.pi * t / p + rng.uniform(0, 2 * np.pi)) / 3
    return out * 1.4


def _rot_y(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _rot_z(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


# ----------------------------------------------------------------------------- ray casting
_NBINS = 2048


def _azimuth_intervals(p: _Prisms, ox: float, oz: float) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth interval [lo, hi] (radians, hi >= lo, possibly beyond +-pi) of each footprint seen from (ox, oz)."""
    box = p.kind == BOX
    cx = np.where(box, 0.5 * (p.a[:, 0] + p.a[:, 1]), p.a[:, 0])
    cz = np.where(box, 0.5 * (p.a[:, 2] + p.a[:, 3]), p.a[:, 1])
    centre = np.arctan2(cx - ox, cz - oz)
    lo = np.empty(len(p))
    hi = np.empty(len(p))
    # boxes: the extreme corner azimuths relative to the centre direction
    corners_x = p.a[:, [0, 1, 0, 1]]
    corners_z = p.a[:, [2, 2, 3, 3]]
    ang = np.arctan2(corners_x - ox, corners_z - oz) - centre[:, None]
    ang = (ang + np.pi) % (2 * np.pi) - np.pi
    lo_box, hi_box = ang.min(1), ang.max(1)
    inside = box & (ox >= p.a[:, 0]) & (ox <= p.a[:, 1]) & (oz >= p.a[:, 2]) & (oz <= p.a[:, 3])
    # cylinders: centre +- asin(r / distance)
    dist = np.hypot(cx - ox, cz - oz)
    half = np.arcsin(np.clip(p.a[:, 2] / np.maximum(dist, 1e-9), 0, 1))
    inside |= ~box & (dist <= p.a[:, 2])
    lo = np.where(box, lo_box, -half) + centre
    hi = np.where(box, hi_box, half) + centre
    lo = np.where(inside, -np.pi, lo)
    hi = np.where(inside, np.pi, hi)
    return lo, hi


def _footprint_distance(p: _Prisms, ox: float, oz: float) -> np.ndarray:
    box = p.kind == BOX
    dx = np.maximum(np.maximum(p.a[:, 0] - ox, ox - p.a[:, 1]), 0)
    dz = np.maximum(np.maximum(p.a[:, 2] - oz, oz - p.a[:, 3]), 0)
    d_box = np.hypot(dx, dz)
    d_cyl = np.maximum(np.hypot(p.a[:, 0] - ox, p.a[:, 1] - oz) - p.a[:, 2], 0)
    return np.where(box, d_box, d_cyl)


def _cast(p: _Prisms, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + t dirs`` ([P,3]) with the prisms and the ground plane y = 0.

    Returns ``(t [P] (inf: sky), object index [P] (-1: ground or sky), face [P])``; face 0/1: box side with
    normal along x/z, 2: top, 3: cylinder side.

    Candidates are found per azimuth bin (the objects whose footprint covers the ray's azimuth) and tested
    in rounds, nearest footprint first. A ray leaves the rounds as soon as no remaining candidate can beat
    its best hit: their footprints start farther away than that hit, or they are all too low for a ray
    climbing at its slope.
    """
    ox, oy, oz = origin
    P = len(dirs)
    dirs = dirs.astype(np.float32)
    rho = np.hypot(dirs[:, 0], dirs[:, 2])  # horizontal length of each direction
    with np.errstate(divide="ignore", invalid="ignore"):
        t_best = np.where(dirs[:, 1] > 1e-9, np.float32(-oy) / dirs[:, 1], np.float32(np.inf))  # the ground
        slope = dirs[:, 1] / rho
    obj = np.full(P, -1, np.int64)
    face = np.full(P, 2, np.int8)
    dist = _footprint_distance(p, ox, oz)
    idx = np.nonzero(dist < _MAX_RANGE)[0]
    if len(idx) == 0:
        return t_best, obj, face
    sub = _Prisms(*(getattr(p, f)[idx] for f in _PRISM_FIELDS))
    cast_sub = _Prisms(
        *(
            getattr(sub, f).astype(np.float32) if f in ("a", "y_top", "y_bot") else getattr(sub, f)
            for f in _PRISM_FIELDS
        )
    )
    origin32 = origin.astype(np.float32)
    near = dist[idx]
    with np.errstate(divide="ignore"):
        sigma = np.where(near > 1e-9, (sub.y_top - oy) / near, -np.inf)  # climb needed to pass over its top
    lo, hi = _azimuth_intervals(sub, ox, oz)
    scale = _NBINS / (2 * np.pi)
    # one spare bin on each side, so that a ray whose azimuth is rounded into a neighbouring bin still
    # finds the object
    b_lo = np.floor((lo + np.pi) * scale).astype(np.int64) - 1
    b_hi = np.floor((hi + np.pi) * scale).astype(np.int64) + 1
    span = np.minimum(b_hi - b_lo + 1, _NBINS)
    cand = np.repeat(np.arange(len(idx)), span)
    cand_bin = (
        np.repeat(b_lo, span) + np.arange(len(cand)) - np.repeat(np.cumsum(span) - span, span)
    ) % _NBINS
    order = np.lexsort((near[cand], cand_bin))  # by bin, then nearest first
    cand, cand_bin = cand[order], cand_bin[order]
    counts = np.bincount(cand_bin, minlength=_NBINS)
    rank = np.arange(len(cand)) - np.repeat(np.cumsum(counts) - counts, counts)
    k_max = int(counts.max())
    table = np.full((_NBINS, k_max + 1), -1, np.int64)  # a -1 column ends every list
    table[cand_bin, rank] = cand
    near_t = np.full((_NBINS, k_max + 1), np.inf)
    near_t[cand_bin, rank] = near[cand]
    sig_t = np.full((_NBINS, k_max + 1), np.inf)
    sig_t[cand_bin, rank] = sigma[cand]
    sig_t = np.minimum.accumulate(sig_t[:, ::-1], axis=1)[:, ::-1]  # lowest climb among the rest

    phi = np.arctan2(dirs[:, 0], dirs[:, 2])
    pix_bin = np.floor((phi + np.float32(np.pi)) * np.float32(scale)).astype(np.int32) & (_NBINS - 1)
    act = np.arange(P)
    for r in range(k_max + 1):
        b = pix_bin[act]
        c = table[b, r]
        # (the climb test holds for rays that do not descend: a descending ray can still drop onto a
        # low roof behind the footprint's nearest point)
        climb = (slope[act] > 0) | (slope[act] >= sig_t[b, r])
        keep = (c >= 0) & (near_t[b, r] < t_best[act] * rho[act]) & climb
        act, c = act[keep], c[keep]
        if len(act) == 0:
            break
        t_hit, f_hit = _intersect(cast_sub, c, origin32, dirs[act])
        better = t_hit < t_best[act]
        win = act[better]
        t_best[win] = t_hit[better]
        obj[win] = idx[c[better]]
        face[win] = f_hit[better]
    return t_best, obj, face


def _intersect(p: _Prisms, k: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-prism intersections for pairs (prism k[i], ray d[i]) -> (t [n] or inf, face [n]).

    Slab tests in float32; a zero direction component divides to +-inf, which the slab logic handles
    (``fmin``/``fmax`` ignore the NaN of a ray lying exactly in a slab's plane).
    """
    n = len(k)
    t = np.full(n, np.inf, np.float32)
    face = np.zeros(n, np.int8)
    ox, oy, oz = o
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for kind in (BOX, CYLINDER):
            sel = np.nonzero(p.kind[k] == kind)[0]
            if len(sel) == 0:
                continue
            kk = k[sel]
            dx, dy, dz = d[sel, 0], d[sel, 1], d[sel, 2]
            a = p.a[kk]
            inv_y = 1 / dy
            ty1 = (p.y_top[kk] - oy) * inv_y
            ty2 = (p.y_bot[kk] - oy) * inv_y
            ty_in, ty_out = np.fmin(ty1, ty2), np.fmax(ty1, ty2)
            if kind == BOX:
                inv_x, inv_z = 1 / dx, 1 / dz
                tx1 = (a[:, 0] - ox) * inv_x
                tx2 = (a[:, 1] - ox) * inv_x
                tz1 = (a[:, 2] - oz) * inv_z
                tz2 = (a[:, 3] - oz) * inv_z
                tx_in, tz_in = np.fmin(tx1, tx2), np.fmin(tz1, tz2)
                side_in = np.fmax(tx_in, tz_in)
                side_out = np.fmin(np.fmax(tx1, tx2), np.fmax(tz1, tz2))
                side_face = np.where(tx_in > tz_in, 0, 1).astype(np.int8)
            else:  # |o_xz + t d_xz - c|^2 = r^2
                ex, ez = ox - a[:, 0], oz - a[:, 1]
                qa = dx * dx + dz * dz
                qb = ex * dx + ez * dz
                qc = ex * ex + ez * ez - a[:, 2] * a[:, 2]
                disc = qb * qb - qa * qc
                root = np.sqrt(np.maximum(disc, 0))
                side_in = np.where(disc >= 0, (-qb - root) / qa, np.inf)
                side_out = np.where(disc >= 0, (-qb + root) / qa, -np.inf)
                side_face = np.full(len(sel), 3, np.int8)
            t_in = np.fmax(side_in, ty_in)
            hit = (t_in <= np.fmin(side_out, ty_out)) & (t_in > 1e-5)
            t[sel] = np.where(hit, t_in, np.inf)
            face[sel] = np.where(ty_in > side_in, 2, side_face)
    return t, face


# ----------------------------------------------------------------------------- shading
def _shade(
    scene: StreetScene,
    p: _Prisms,
    pts: np.ndarray,
    dirs: np.ndarray,
    t: np.ndarray,
    obj: np.ndarray,
    face: np.ndarray,
    pixel_angle: float,
) -> np.ndarray:
    """Colour [P,3] float32 in [0, 1] of the hit points ``pts`` (sky where ``t`` is inf).

    Textures are filtered over the pixel's footprint on the surface (``pixel_angle`` radians per pixel
    times the distance, stretched at grazing angles), so distant detail averages out instead of aliasing.
    """
    f32 = np.float32
    P = len(t)
    out = np.zeros((P, 3), f32)
    sky = ~np.isfinite(t)
    length = np.linalg.norm(dirs, axis=1)
    unit = dirs / length[:, None]
    # ---- sky: a gradient and soft clouds, functions of the direction only (at infinity)
    if sky.any():
        d = unit[sky]
        up = np.clip(-d[:, 1], 0, 1)
        base = np.array([0.78, 0.86, 0.95], f32) + up[:, None] * np.array([-0.43, -0.31, -0.10], f32)
        k = f32(40) / (f32(0.25) + up)
        cloud = scene.sky_tile.sample(d[:, 0] * k, d[:, 2] * k, 1.0, k * f32(pixel_angle))
        cloud = _smoothstep(0.5, 0.75, cloud)[:, None]
        out[sky] = base * (1 - f32(0.7) * cloud) + f32(0.68) * cloud
    dist = np.where(sky, 0, t * length).astype(f32)
    cone = f32(pixel_angle) * dist
    ground = np.nonzero(~sky & (obj < 0))[0]
    if len(ground):
        cos = np.abs(unit[ground, 1])
        fp = cone[ground] / np.sqrt(np.maximum(cos, f32(0.02)))
        light = f32(0.55 + 0.55 * -_SUN[1])
        out[ground] = _ground_colour(scene, pts[ground, 0], pts[ground, 2], fp) * light
    objs = np.nonzero(~sky & (obj >= 0))[0]
    if len(objs):
        out[objs] = _object_colour(scene, p, pts[objs], obj[objs], face[objs], unit[objs], cone[objs])
    return np.clip(out, 0, 1)


def _object_colour(
    scene: StreetScene,
    p: _Prisms,
    pts: np.ndarray,
    k: np.ndarray,
    f: np.ndarray,
    unit: np.ndarray,
    cone: np.ndarray,
) -> np.ndarray:
    """Lit colour [n,3] of object surface points [n,3] on prisms ``k`` and faces ``f``."""
    f32 = np.float32
    tiles = scene.tiles
    px, py, pz = pts[:, 0], pts[:, 1], pts[:, 2]
    mat = p.material[k]
    base = p.colour[k].astype(f32)
    # surface coordinates (su along the surface, sv up) and the normal
    top = f == 2
    cyl = f == 3
    su = np.where(f == 0, pz, px)
    sv = np.where(top, pz, -py)
    nx = np.where(f == 0, np.sign(px - f32(0.5) * (p.a[k, 0] + p.a[k, 1])), 0).astype(f32)
    nz = np.where(f == 1, np.sign(pz - f32(0.5) * (p.a[k, 2] + p.a[k, 3])), 0).astype(f32)
    ny = np.where(top, np.where(py < 0.5 * (p.y_top[k] + p.y_bot[k]), -1, 1), 0).astype(f32)
    if cyl.any():
        ang = np.arctan2(px[cyl] - p.a[k[cyl], 0], pz[cyl] - p.a[k[cyl], 1]).astype(f32)
        nx[cyl] = np.sin(ang)
        nz[cyl] = np.cos(ang)
        su[cyl] = ang * p.a[k[cyl], 2]
    cos = np.abs(nx * unit[:, 0] + ny * unit[:, 1] + nz * unit[:, 2])
    fp = cone / np.sqrt(np.maximum(cos, f32(0.02)))  # footprint on the surface, metres
    fine = tiles["fine"].sample(su, sv, 40.0, fp)
    coarse = tiles["coarse"].sample(su, sv, 6.0, fp)
    # most materials: base colour times a scalar texture
    col = base * (f32(0.85) + f32(0.3) * fine)[:, None]
    fac = np.nonzero((mat == FACADE) & ~top)[0]
    if len(fac):
        col[fac] = _facade_colour(
            base[fac], p.param[k[fac]].astype(f32), su[fac], sv[fac], fine[fac], coarse[fac], fp[fac]
        )
    for m, lo, amp, tex in (
        (CAR_UNDER, 0.3, 1.5, fine),
        (CAR_GLASS, 0.7, 0.6, coarse),
        (POLE, 0.8, 0.4, fine),
    ):
        sel = mat == m
        col[sel] = base[sel] * (f32(lo) + f32(amp) * tex[sel])[:, None]
    roof = np.nonzero((mat == FACADE) & top)[0]
    col[roof] = ((0.45 + 0.2 * coarse[roof]) * (0.6 + 0.8 * fine[roof]))[:, None] * np.array(
        [0.9, 0.88, 0.85], f32
    )
    trunk = np.nonzero(mat == TRUNK)[0]
    bark = tiles["fine"].sample(su[trunk] * f32(0.5), sv[trunk] * f32(3), 40.0, fp[trunk] * f32(3))
    col[trunk] = base[trunk] * (0.6 + 0.8 * bark)[:, None]
    crown = np.nonzero(mat == CROWN)[0]
    leaves = tiles["leaves"].sample(su[crown], sv[crown], 12.0, fp[crown])
    col[crown] = base[crown] * ((0.45 + 1.1 * leaves) * (0.85 + 0.3 * coarse[crown]))[:, None]
    # sun (Lambert) + sky ambient, a little darker near the ground
    sun = _SUN.astype(f32)
    lam = np.clip(nx * sun[0] + ny * sun[1] + nz * sun[2], 0, 1)
    light = (f32(0.55) + f32(0.1) * np.clip(-ny, 0, 1) + f32(0.55) * lam) * (
        f32(0.85) + f32(0.15) * _smoothstep(0.0, 2.5, -py)
    )
    return col * light[:, None]


def _facade_colour(base, par, su, sv, fine, coarse, fp) -> np.ndarray:
    """Facade colour [n,3]: plaster, brick or concrete wall with a grid of windows and a plinth.

    Every pattern is box-filtered over the footprint ``fp`` (metres), so it fades to its average with
    distance instead of aliasing.
    """
    f32 = np.float32
    floor_h, pitch, style, seed = par[:, 0], par[:, 1], par[:, 2], par[:, 3]
    tone = (0.8 + 0.25 * coarse) * (0.85 + 0.3 * fine)
    # bricks: courses of 0.085 m, bricks 0.25 m long (staggered), with light mortar joints
    brick = style == 1
    course = f32(0.085)
    row = np.floor(sv / course)
    shift = f32(0.125) * (row % 2)
    detail = 1 - _smoothstep(0.03, 0.1, fp)  # per-brick variation fades once bricks are sub-pixel
    tint = 1 + (0.3 * _hash01(np.floor((su + shift) / f32(0.25)), row, seed) - 0.15).astype(f32) * detail
    mortar = 1 - (1 - _pulse(sv, course, 0.0, 0.1, fp)) * (1 - _pulse(su + shift, f32(0.25), 0.0, 0.06, fp))
    tone = np.where(brick, tone * tint, tone)
    # concrete panels: a coarse grid of dark joints
    joints = 1 - (1 - _pulse(su, f32(1.5), 0.0, 0.015, fp)) * (1 - _pulse(sv, f32(1.2), 0.0, 0.02, fp))
    tone = np.where(style == 2, tone * (1 - 0.4 * joints), tone)
    tone = tone * (1 - 0.3 * _band(sv, -1.0, 0.6, fp))  # a darker plinth
    col = base * tone[:, None]
    mortar = np.where(brick, mortar, 0)[:, None]
    col = col * (1 - mortar) + mortar * np.array([0.52, 0.51, 0.48], f32)
    # windows on a grid of floors and bays (none below 0.9 m): frame, then glass inside it
    above = _band(sv, 0.9, 1e4, fp)
    win = _pulse(su, pitch, 0.22, 0.78, fp) * _pulse(sv, floor_h, 0.30, 0.82, fp) * above
    pane = _pulse(su, pitch, 0.26, 0.74, fp) * _pulse(sv, floor_h, 0.34, 0.78, fp) * above
    lit = _hash01(np.floor(su / pitch), np.floor(sv / floor_h), seed).astype(f32)
    lit = lit + (f32(0.5) - lit) * _smoothstep(0.3, 1.0, fp / pitch)  # windows blend once sub-pixel
    cv = sv / floor_h - np.floor(sv / floor_h)
    glass = (np.array([0.15, 0.18, 0.22], f32) + lit[:, None] * np.array([0.25, 0.25, 0.3], f32)) * (
        0.8 + 0.4 * fine
    )[:, None] + (f32(0.25) * (np.clip(cv, 0.3, 0.82) - f32(0.3)) * (1 - _smoothstep(0.5, 1.5, fp)))[:, None]
    frame = (win - pane)[:, None]
    return col * (1 - win)[:, None] + f32(0.85) * frame + glass * pane[:, None]


_GROUND_COLOURS = np.array(
    [
        [1.0, 1.0, 1.02],  # 0 asphalt
        [0.95, 0.93, 0.9],  # 1 paving
        [0.35, 0.55, 0.22],  # 2 grass
        [0.75, 0.7, 0.62],  # 3 gravel
    ],
    np.float32,
)


def _ground_colour(scene: StreetScene, x: np.ndarray, z: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Unlit ground colour [n,3] at world points (x, z) with footprint ``fp`` (metres): roads with
    markings, sidewalks with paving, parks. Markings and joints are box-filtered over the footprint."""
    f32 = np.float32
    cfg = scene.config
    rw, sw = f32(cfg.road_half_width), f32(cfg.sidewalk_width)
    tiles = scene.tiles
    # lateral offsets from the nearest street centre lines in both directions
    xs, zs = scene.xs.astype(f32), scene.zs.astype(f32)
    ix = np.clip(np.searchsorted(xs, x), 1, len(xs) - 1)
    dx = np.where(np.abs(x - xs[ix - 1]) < np.abs(x - xs[ix]), x - xs[ix - 1], x - xs[ix])
    iz = np.clip(np.searchsorted(zs, z), 1, len(zs) - 1)
    dz = np.where(np.abs(z - zs[iz - 1]) < np.abs(z - zs[iz]), z - zs[iz - 1], z - zs[iz])
    adx, adz = np.abs(dx), np.abs(dz)
    on_z, on_x = adx < rw, adz < rw
    road = on_z | on_x
    walk = ~road & ((adx < rw + sw) | (adz < rw + sw))
    asphalt = tiles["asphalt"].sample(x, z, 30.0, fp)
    fine = tiles["fine"].sample(x, z, 60.0, fp)
    kind = np.full(len(x), 3, np.int8)
    tone = f32(0.45) + f32(0.3) * asphalt
    r = np.nonzero(road)[0]
    if len(r):
        fr, xr, zr, dxr, dzr, axr, azr = fp[r], x[r], z[r], dx[r], dz[r], adx[r], adz[r]
        oz, ox = on_z[r], on_x[r]
        cross = oz & ox
        # markings: dashed centre lines, solid edge lines, zebra crossings before the intersections
        centre_z = np.where(oz & ~cross, _band(dxr, -0.08, 0.08, fr) * _pulse(zr, f32(6), 0.0, 0.5, fr), 0)
        centre_x = np.where(ox & ~cross, _band(dzr, -0.08, 0.08, fr) * _pulse(xr, f32(6), 0.0, 0.5, fr), 0)
        edge_z = np.where(oz & ~ox, _band(axr, rw - 0.42, rw - 0.28, fr), 0)
        edge_x = np.where(ox & ~oz, _band(azr, rw - 0.42, rw - 0.28, fr), 0)
        zebra_z = np.where(oz, _band(azr, rw + 0.5, rw + 3.5, fr) * _pulse(dxr, f32(1.2), 0.0, 0.5, fr), 0)
        zebra_x = np.where(ox, _band(axr, rw + 0.5, rw + 3.5, fr) * _pulse(dzr, f32(1.2), 0.0, 0.5, fr), 0)
        paint = np.clip(centre_z + centre_x + edge_z + edge_x + zebra_z + zebra_x, 0, 1)
        coarse = tiles["coarse"].sample(xr, zr, 2.0, fr)
        asph = f32(0.22) + f32(0.25) * asphalt[r] + f32(0.08) * coarse
        tone[r] = asph * (1 - paint) + (f32(0.78) + f32(0.15) * fine[r]) * paint
        kind[r] = 0
    # sidewalks: 0.5 m paving slabs with dark joints, and a kerb stone
    w = np.nonzero(walk)[0]
    if len(w):
        fw = fp[w]
        su, sv = x[w], z[w]
        joint = 1 - (1 - _pulse(su, f32(0.5), 0.0, 0.04, fw)) * (1 - _pulse(sv, f32(0.5), 0.0, 0.04, fw))
        detail = 1 - _smoothstep(0.15, 0.5, fw)
        slab = 0.61 + (0.12 * _hash01(np.floor(su / 0.5), np.floor(sv / 0.5), 7) - 0.06).astype(f32) * detail
        slab = slab + 0.15 * (fine[w] - 0.5)
        slab = slab * (1 - joint) + f32(0.38) * joint
        kerb = np.clip(
            _band(adx[w], rw - 0.18, rw + 0.18, fw) + _band(adz[w], rw - 0.18, rw + 0.18, fw), 0, 1
        )
        tone[w] = slab * (1 - kerb) + (f32(0.7) + f32(0.1) * fine[w]) * kerb
        kind[w] = 1
    # inside the blocks: grass in parks, gravel elsewhere
    inner = np.nonzero(~road & ~walk)[0]
    if len(inner) and scene.park_blocks.any():
        bi = np.clip(np.searchsorted(scene.xs, x[inner]) - 1, 0, len(scene.xs) - 2)
        bj = np.clip(np.searchsorted(scene.zs, z[inner]) - 1, 0, len(scene.zs) - 2)
        park = inner[scene.park_blocks[bi, bj]]
        kind[park] = 2
        tone[park] = f32(0.35) + f32(0.5) * tiles["leaves"].sample(x[park], z[park], 25.0, fp[park])
    return _GROUND_COLOURS[kind] * tone[:, None]


# ----------------------------------------------------------------------------- rendering
def make_camera(
    projection: str, width: int, height: int, vfov_h: float = 1.0, pinhole_fov: float = 90.0
) -> Camera:
    """The camera of a generated dataset for ``projection`` in cylindrical | equirect | pinhole."""
    if projection == "cylindrical":
        return CylindricalCamera.full(width, height, vfov_h)
    if projection in ("equirect", "equirectangular"):
        return EquirectangularCamera.full(width, height)
    if projection == "pinhole":
        return PinholeCamera.from_fov(width, height, pinhole_fov)
    raise ValueError(f"unknown projection {projection!r} (expected cylindrical, equirect or pinhole)")


def _camera_rays(camera: Camera, supersample: int) -> np.ndarray:
    """Camera-frame rays (unit model depth, float32) ``[R,3]`` whose colours :func:`_resolve` forms pixels of.

    The last ``H*W`` rays are the pixel centres (their hits are the depth). ``supersample = 1`` is the
    quincunx pattern: each pixel is 1/2 its centre plus 1/8 of each of its 4 corners, which neighbouring
    pixels share (2 rays a pixel for 5 samples). ``supersample = n >= 2``: an ``n x n`` grid in every pixel
    (plus the centre for depth).
    """
    import torch

    h, w = camera.height, camera.width
    grid = camera.pixel_grid(1, dtype=torch.float64)
    centre = camera.rays(grid)[0].permute(1, 2, 0).reshape(-1, 3).numpy()
    if supersample <= 1:
        v, u = np.meshgrid(np.arange(h + 1) - 0.5, np.arange(w + 1) - 0.5, indexing="ij")
        uv = torch.from_numpy(np.stack((u, v))[None])
        corners = camera.rays(uv)[0].permute(1, 2, 0).reshape(-1, 3).numpy()
        rays = np.concatenate([corners, centre])
    else:
        s = supersample
        offs = (np.arange(s) + 0.5) / s - 0.5
        subs = []
        for oy in offs:
            for ox in offs:
                shifted = grid + torch.tensor([ox, oy], dtype=torch.float64).view(1, 2, 1, 1)
                subs.append(camera.rays(shifted)[0].permute(1, 2, 0).reshape(-1, 3).numpy())
        rays = np.concatenate([*subs, centre])
    return rays.astype(np.float32)


def _resolve(colour: np.ndarray, h: int, w: int, supersample: int) -> np.ndarray:
    """Pixels ``[h,w,3]`` from the colours of :func:`_camera_rays`' rays (centre rays last)."""
    if supersample <= 1:
        c = colour[: (h + 1) * (w + 1)].reshape(h + 1, w + 1, 3)
        centre = colour[-h * w :].reshape(h, w, 3)
        return 0.5 * centre + 0.125 * (c[:-1, :-1] + c[:-1, 1:] + c[1:, :-1] + c[1:, 1:])
    s2 = supersample * supersample
    return colour[: s2 * h * w].reshape(s2, h, w, 3).mean(0)


_RAY_CACHE: dict[tuple, np.ndarray] = {}


def render_frame(
    scene: StreetScene, frame: int, camera: Camera, supersample: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Render ``frame`` of ``scene``'s ride: ``(image uint8 [H,W,3], depth float32 [H,W])``.

    Depth is the camera model's depth of the surface seen at each pixel centre (cylindrical: horizontal
    distance; pinhole: z; equirectangular: range), in metres, 0 for the sky. ``supersample`` overrides the
    scene's anti-aliasing (see :class:`SynthConfig`).
    """
    s = supersample or scene.config.supersample
    key = (
        type(camera).__name__,
        *camera.size,
        *(float(v) for v in (camera.fx, camera.cx, camera.fy, camera.cy)),
        s,
    )
    if key not in _RAY_CACHE:
        _RAY_CACHE.clear()
        _RAY_CACHE[key] = _camera_rays(camera, s)
    rays = _RAY_CACHE[key]
    c2w = scene.c2w[frame]
    rot, origin = c2w[:3, :3].astype(np.float32), c2w[:3, 3]
    prisms = scene.prisms_at(frame)
    # d = R r written out: a BLAS matmul would start threads, which oversubscribe the render workers
    dirs = rays[:, 0:1] * rot[:, 0] + rays[:, 1:2] * rot[:, 1] + rays[:, 2:3] * rot[:, 2]
    t, obj, face = _cast(prisms, origin, dirs)
    finite = np.isfinite(t)
    pts = origin.astype(np.float32) + np.where(finite, t, 0)[:, None] * dirs
    h, w = camera.height, camera.width
    shaded = len(rays) if s <= 1 else len(rays) - h * w  # the grid pattern does not shade the centres
    pixel_angle = scene.config.texture_filter / float(camera.fx)
    colour = _shade(
        scene, prisms, pts[:shaded], dirs[:shaded], t[:shaded], obj[:shaded], face[:shaded], pixel_angle
    )
    image = _resolve(colour, h, w, s)
    image = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    t_c = t[-h * w :]
    depth = np.where(np.isfinite(t_c), t_c, 0.0).reshape(h, w).astype(np.float32)
    return image, depth


# ----------------------------------------------------------------------------- datasets
_WORKER: dict = {}


def _init_worker(scene: StreetScene, camera: Camera) -> None:
    import torch

    torch.set_num_threads(1)  # one process per core: no threads inside
    _WORKER["scene"], _WORKER["camera"] = scene, camera


def _render_job(frame: int) -> tuple[int, np.ndarray, np.ndarray]:
    image, depth = render_frame(_WORKER["scene"], frame, _WORKER["camera"])
    return frame, image, depth


def generate_dataset(
    out: str | os.PathLike[str],
    sequences: int = 4,
    frames: int = 200,
    width: int = 512,
    height: int = 128,
    seed: int = 0,
    moving_objects: bool = False,
    projection: str = "cylindrical",
    workers: int | None = None,
    config: SynthConfig | None = None,
    progress: bool = True,
    first_index: int = 0,
    overwrite: bool = False,
) -> list[Path]:
    """Write ``sequences`` rides of ``frames`` frames each to ``out/seq_NNN`` in dataset format v1.

    Each sequence is a different town and ride (seeded by ``seed`` and the sequence index). Frames are
    rendered in parallel by ``workers`` processes (default: the number of CPUs). Returns the sequence
    directories.
    """
    from concurrent.futures import ProcessPoolExecutor

    from .format import SequenceWriter

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    camera = make_camera(projection, width, height)
    workers = workers or os.cpu_count() or 1
    dirs = []
    base = config or SynthConfig()
    for n in range(first_index, first_index + sequences):
        cfg = replace(base, frames=frames, moving_cars=base.moving_cars or (12 if moving_objects else 0))
        scene = StreetScene.generate(int(np.random.SeedSequence([seed, n]).generate_state(1)[0]), cfg)
        seq_dir = out / f"seq_{n:03d}"
        writer = SequenceWriter(seq_dir, camera, overwrite=overwrite)
        results: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        nxt = 0
        bar = _progress(frames, f"seq_{n:03d}") if progress else None
        if workers > 1:
            with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(scene, camera)) as pool:
                for f, image, depth in pool.map(_render_job, range(frames), chunksize=4):
                    results[f] = (image, depth)
                    while nxt in results:
                        writer.add_frame(*results.pop(nxt))
                        nxt += 1
                        if bar:
                            bar.update(1)
        else:
            _init_worker(scene, camera)
            for f in range(frames):
                _, image, depth = _render_job(f)
                writer.add_frame(image, depth)
                if bar:
                    bar.update(1)
        if bar:
            bar.close()
        writer.finish(scene.c2w, np.arange(frames) / cfg.fps)
        dirs.append(seq_dir)
    return dirs


def _progress(total: int, desc: str):
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency, but stay usable without it
        return None
    return tqdm(total=total, desc=desc, unit="frame", leave=False)
