"""The town: a grid of streets, blocks of buildings (or parks), street furniture, the ride and its traffic.

A town is a grid of streets (their centre lines ``xs`` along z and ``zs`` along x) with corridors of road
and sidewalk, and blocks between them: buildings along the four sides of a block and a lower filler in
its middle, or now and then a park of trees. Parked cars line the kerbs, lamps and trees the sidewalks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .cars import MovingCar, add_car, car_colour, moving_cars
from .config import SynthConfig
from .prisms import BOX, CROWN, CYLINDER, FACADE, POLE, TRUNK, Prisms, prisms_from_rows
from .ride import route_poses
from .textures import TILE, Mip, periodic_noise

__all__ = ["StreetScene"]


@dataclass
class StreetScene:
    """A town (streets, blocks, objects), its moving cars and the camera's route.

    Build one with :meth:`generate`; render frames with :func:`~cylsfm.data.synth.render_frame`.
    """

    seed: int
    config: SynthConfig
    xs: np.ndarray  # centre lines of the streets running along z (their x), sorted
    zs: np.ndarray  # centre lines of the streets running along x (their z), sorted
    static: Prisms
    movers: list[MovingCar] = field(default_factory=list)  # the cars driving through the town
    c2w: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # [F, 4, 4] camera-to-world
    tiles: dict[str, Mip] = field(default_factory=dict)
    sky_tile: Mip | None = None
    park_blocks: np.ndarray = field(default_factory=lambda: np.zeros((1, 1), bool))  # [i, j] block is a park

    @classmethod
    def generate(cls, seed: int, config: SynthConfig | None = None) -> StreetScene:
        """The town, ride and traffic of ``seed`` (a pure function of ``seed`` and ``config``)."""
        cfg = config or SynthConfig()
        rng = np.random.default_rng(seed)
        corridor = cfg.road_half_width + cfg.sidewalk_width
        town = cfg.town_frames or cfg.frames
        n_blocks = int(np.clip(math.ceil(math.sqrt(town * cfg.speed) / 3.5) + 3, 4, 14))
        gaps = rng.uniform(*cfg.block_size, size=(2, n_blocks)) + 2 * corridor
        xs = np.concatenate(([0.0], np.cumsum(gaps[0])))
        zs = np.concatenate(([0.0], np.cumsum(gaps[1])))
        xs -= xs.mean()
        zs -= zs.mean()
        tiles = {
            "asphalt": Mip(periodic_noise(rng, TILE, 0.6)),
            "fine": Mip(periodic_noise(rng, TILE, 0.3)),
            "coarse": Mip(periodic_noise(rng, TILE, 1.4)),
            "leaves": Mip(periodic_noise(rng, TILE, 0.2)),
        }
        sky_tile = Mip(periodic_noise(rng, TILE, 1.6))
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
        if cfg.alike:  # one colour and one facade for every building (drawn after: the layout is kept)
            colour, facade = _building_colour(rng), _facade(rng)
            rows = [(*r[:5], colour, facade) if r[4] == FACADE else r for r in rows]
        static = prisms_from_rows(rows)
        scene = cls(seed, cfg, xs, zs, static, tiles=tiles, sky_tile=sky_tile, park_blocks=park_blocks)
        scene.c2w = route_poses(rng, cfg, xs, zs)
        scene.movers = moving_cars(rng, cfg, xs, zs, scene.c2w)
        return scene

    def prisms_at(self, frame: int) -> Prisms:
        """Static objects plus the moving cars at their positions in ``frame`` (3 prisms a car, last)."""
        if not self.movers:
            return self.static
        rows: list[tuple] = []
        for car in self.movers:
            car.add_rows(rows, frame)
        return Prisms.concat([self.static, prisms_from_rows(rows)])


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
    """Trees scattered over a block, one per 120 square metres."""
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
    """A tree at (x, z): a trunk and a cylindrical crown."""
    r = float(rng.uniform(1.4, 2.6))
    trunk_h = float(rng.uniform(2.2, 3.2))
    crown_h = float(rng.uniform(3.0, 6.0))
    seed = float(rng.integers(1 << 30))
    green = tuple(
        np.clip(np.array([0.25, 0.45, 0.18]) * rng.uniform(0.7, 1.3) + rng.normal(0, 0.03, 3), 0, 1)
    )
    rows.append((CYLINDER, (x, z, 0.2, 0), -trunk_h - 0.5, 0.0, TRUNK, (0.35, 0.25, 0.17), (0, 0, 0, seed)))
    rows.append((CYLINDER, (x, z, r, 0), -trunk_h - crown_h, -trunk_h, CROWN, green, (0, 0, 0, seed)))


def _street_furniture(rng, rows, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray) -> None:
    """Parked cars along the kerbs, lamps and trees along the sidewalks."""
    corridor = cfg.road_half_width + cfg.sidewalk_width
    for axis, lines, cross in (("z", xs, zs), ("x", zs, xs)):
        for line in lines:
            for k in range(len(cross) - 1):
                lo, hi = cross[k] + corridor + 2, cross[k + 1] - corridor - 2
                for side in (-1, 1):
                    _parked_cars(rng, rows, cfg, axis, line, side, lo, hi)
                    _lamps_and_trees(rng, rows, cfg, axis, line, side, lo, hi)


def _parked_cars(
    rng, rows, cfg: SynthConfig, axis: str, line: float, side: int, lo: float, hi: float
) -> None:
    """Parked cars in the kerb lane on ``side`` (-1 or 1) of a street stretch ``[lo, hi]``."""
    pos = lo + rng.uniform(0, 4)
    while pos < hi - 5:
        if rng.random() < 0.45:
            off = side * (cfg.road_half_width - 1.1)
            cx, cz = (line + off, pos + 2.2) if axis == "z" else (pos + 2.2, line + off)
            add_car(rows, cx, cz, axis, car_colour(rng), float(rng.integers(1 << 30)))
        pos += rng.uniform(5.2, 7.5)


def _lamps_and_trees(
    rng, rows, cfg: SynthConfig, axis: str, line: float, side: int, lo: float, hi: float
) -> None:
    """Street lamps and trees on the sidewalk on ``side`` (-1 or 1) of a street stretch ``[lo, hi]``."""
    rw, sw = cfg.road_half_width, cfg.sidewalk_width
    pos = lo + rng.uniform(0, 10)
    while pos < hi:
        off = side * (rw + 0.6)
        cx, cz = (line + off, pos) if axis == "z" else (pos, line + off)
        if rng.random() < 0.5:
            height = -float(rng.uniform(5, 7))
            rows.append((CYLINDER, (cx, cz, 0.12, 0), height, 0.0, POLE, (0.3, 0.32, 0.33), (0, 0, 0, 0)))
        else:
            off_t = side * (rw + sw * 0.55)
            tx, tz = (line + off_t, pos) if axis == "z" else (pos, line + off_t)
            _tree(rng, rows, tx, tz)
        pos += rng.uniform(12, 28)
