"""Cars: the prisms of a car, parked-car colours, and the cars that drive through the town.

A car is three boxes (underbody, body, glass cabin), 4.3 m long and 1.8 m wide, its length along the
street. Moving cars drive along the lanes at constant speeds and never come closer to the camera's
route than :data:`CLEARANCE` (centre to camera, horizontally, in every frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import SynthConfig
from .prisms import BOX, CAR_BODY, CAR_GLASS, CAR_UNDER

__all__ = ["CLEARANCE", "MovingCar", "add_car", "car_colour", "moving_cars"]

#: The least horizontal distance (metres) between a moving car's centre and the camera in any frame.
CLEARANCE = 3.5


def add_car(rows: list[tuple], x: float, z: float, axis: str, colour, seed: float) -> None:
    """Append the prisms of a car centred at (x, z), its length along ``axis``: underbody, body, glass cabin."""

    def box(half_len, half_wid, yt, yb, mat, col):
        if axis == "z":
            a = (x - half_wid, x + half_wid, z - half_len, z + half_len)
        else:
            a = (x - half_len, x + half_len, z - half_wid, z + half_wid)
        rows.append((BOX, a, yt, yb, mat, col, (0, 0, 0, seed)))

    box(1.75, 0.82, -0.42, 0.0, CAR_UNDER, (0.05, 0.05, 0.05))
    box(2.15, 0.9, -1.0, -0.42, CAR_BODY, colour)
    box(1.2, 0.8, -1.45, -1.0, CAR_GLASS, (0.15, 0.18, 0.22))


def car_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    """A random car paint (RGB in [0, 1])."""
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


@dataclass(frozen=True)
class MovingCar:
    """A car driving along a street lane at a constant speed; it wraps around from one end of the town to
    the other.

    Attributes:
        axis: ``"z"`` or ``"x"``, the direction of its street.
        line: the street's centre line (its x for a street along z, its z for a street along x), metres.
        offset: the lane's signed offset from the centre line, metres (added to ``line``).
        start: its position along the street in frame 0, metres.
        speed: signed metres per frame.
        extent: ``(lo, hi)``, the stretch of the street it drives along, metres.
        colour: body paint, RGB in [0, 1].
        seed: the texture seed of its surfaces.
    """

    axis: str
    line: float
    offset: float
    start: float
    speed: float
    extent: tuple[float, float]
    colour: tuple[float, float, float]
    seed: float

    def along(self, frame: np.ndarray | int) -> np.ndarray:
        """Position (metres) along its street at ``frame`` (int or int [F]): float64, the shape of ``frame``."""
        lo, hi = self.extent
        return lo + (self.start + self.speed * np.asarray(frame, np.float64) - lo) % (hi - lo)

    def centres(self, frames: np.ndarray) -> np.ndarray:
        """Its centre ``(x, z)`` in each of ``frames`` (int [F]): float64 [F, 2], metres."""
        along = self.along(frames)
        pos = np.stack([np.full_like(along, self.line + self.offset), along], 1)
        return pos[:, ::-1] if self.axis == "x" else pos

    def add_rows(self, rows: list[tuple], frame: int) -> None:
        """Append its prisms at their positions in ``frame``."""
        along = float(self.along(frame))
        if self.axis == "z":
            add_car(rows, self.line + self.offset, along, "z", self.colour, self.seed)
        else:
            add_car(rows, along, self.line + self.offset, "x", self.colour, self.seed)


def moving_cars(
    rng: np.random.Generator, cfg: SynthConfig, xs: np.ndarray, zs: np.ndarray, c2w: np.ndarray
) -> list[MovingCar]:
    """``cfg.moving_cars`` cars driving along the lanes at constant speeds, never through the camera.

    Each car is drawn again (up to 50 times) until its centre stays more than :data:`CLEARANCE` metres
    from the camera (horizontally) in every frame of the ride ``c2w`` ([F, 4, 4] camera-to-world); a car
    with no such draw is left out. ``xs`` and ``zs`` are the streets' centre lines.
    """
    out: list[MovingCar] = []
    cam = c2w[:, [0, 2], 3]
    frames = np.arange(len(c2w))
    for n in range(cfg.moving_cars):
        for _ in range(50):
            axis = "z" if rng.random() < 0.5 else "x"
            lines, cross = (xs, zs) if axis == "z" else (zs, xs)
            line = float(lines[rng.integers(len(lines))])
            direction = 1 if rng.random() < 0.5 else -1
            # drive on the right: the lane centre is 2 m right of the centre line
            offset = float(rng.uniform(1.8, 2.2)) * direction * (1 if axis == "z" else -1)
            start = float(rng.uniform(cross[0], cross[-1]))
            speed = direction * float(rng.uniform(0.8, 2.0))
            extent = (float(cross[0]), float(cross[-1]))
            car = MovingCar(axis, line, offset, start, speed, extent, car_colour(rng), float(1_000_000 + n))
            if np.min(np.linalg.norm(car.centres(frames) - cam, axis=1)) > CLEARANCE:
                out.append(car)
                break
    return out
