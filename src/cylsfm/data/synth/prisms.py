"""The objects of a town: vertical prisms (boxes and cylinders standing on the ground) and their materials.

Every object is a prism between two heights ``y_top < y_bot`` (world y points down, the ground is y = 0)
over a footprint in the x-z plane: an axis-aligned rectangle (a box) or a circle (a cylinder). A set of
objects is a :class:`Prisms`, a struct of arrays; generators append rows (tuples) and turn them into one
with :func:`prisms_from_rows`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "BOX",
    "CAR_BODY",
    "CAR_GLASS",
    "CAR_UNDER",
    "CROWN",
    "CYLINDER",
    "FACADE",
    "POLE",
    "PRISM_FIELDS",
    "ROOF",
    "TRUNK",
    "Prisms",
    "prisms_from_rows",
]

#: Footprint kinds.
BOX, CYLINDER = 0, 1
#: Materials (how :mod:`.shading` colours a surface).
FACADE, ROOF, CAR_BODY, CAR_GLASS, CAR_UNDER, POLE, TRUNK, CROWN = range(8)

#: The fields of :class:`Prisms`, in the order of a row.
PRISM_FIELDS = ("kind", "a", "y_top", "y_bot", "material", "colour", "param")


@dataclass
class Prisms:
    """Struct of arrays of vertical prisms (boxes and cylinders standing between y_top and y_bot)."""

    kind: np.ndarray  # int8 [N]
    a: np.ndarray  # float64 [N, 4]: box x0, x1, z0, z1 | cylinder cx, cz, r, 0
    y_top: np.ndarray  # float64 [N] (negative: above the ground)
    y_bot: np.ndarray  # float64 [N]
    material: np.ndarray  # int8 [N]
    colour: np.ndarray  # float64 [N, 3]
    param: np.ndarray  # float64 [N, 4]: per-material parameters (facade: floor h, window pitch, style, seed)

    @staticmethod
    def concat(parts: list[Prisms]) -> Prisms:
        """The prisms of ``parts``, one after the other."""
        return Prisms(*(np.concatenate([getattr(p, f) for p in parts]) for f in PRISM_FIELDS))

    def take(self, idx: np.ndarray) -> Prisms:
        """The prisms at the indices ``idx`` (int [M])."""
        return Prisms(*(getattr(self, f)[idx] for f in PRISM_FIELDS))

    def __len__(self) -> int:
        return len(self.kind)


def prisms_from_rows(rows: list[tuple]) -> Prisms:
    """:class:`Prisms` from rows ``(kind, a, y_top, y_bot, material, colour, param)``."""
    if not rows:
        return Prisms(
            np.zeros(0, np.int8),
            np.zeros((0, 4)),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, np.int8),
            np.zeros((0, 3)),
            np.zeros((0, 4)),
        )
    kind, a, yt, yb, mat, col, par = zip(*rows, strict=True)
    return Prisms(
        np.array(kind, np.int8),
        np.array(a, np.float64),
        np.array(yt, np.float64),
        np.array(yb, np.float64),
        np.array(mat, np.int8),
        np.array(col, np.float64),
        np.array(par, np.float64),
    )
