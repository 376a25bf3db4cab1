"""The bundle adjustment's sparse points and their tracks as a file, ``points.npz`` (written by
:func:`cylsfm.odometry` beside its trajectory, read by the exports and by training from a ride's own
geometry). It holds plain arrays (no pickled objects):

- ``xyz`` ``float64 [P,3]``: the points in the trajectory's world (the first frame's camera axes, x right,
  y down, z forward) and unit;
- ``rgb`` ``uint8 [P,3]``: their colours;
- ``frame`` ``int64 [N]``, ``point`` ``int64 [N]``, ``uv`` ``float64 [N,2]``: each observation kept by the
  adjustment: the frame (its index in the ride, the row of ``trajectory.txt``), the point, and the
  keypoint in that frame's own pixels (integer ``(u, v)`` at pixel centres);
- ``unit``: the unit's name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CylsfmError

__all__ = ["SparsePoints", "read_points"]


@dataclass(frozen=True)
class SparsePoints:
    """Triangulated points and their tracks (see the module docstring for the arrays' meaning)."""

    xyz: np.ndarray
    rgb: np.ndarray
    frame: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    unit: str


def read_points(path: Path, frames: int, size: tuple[int, int]) -> SparsePoints:
    """The points and tracks of ``path`` (``points.npz``) for a ride of ``frames`` frames of ``size``
    ``(W, H)`` pixels.

    Raises:
        CylsfmError: unreadable, or arrays that do not fit together or the ride (naming the file and the
            problem).
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            got = {k: np.asarray(z[k]) for k in ("xyz", "rgb", "frame", "point", "uv", "unit")}
    except FileNotFoundError:
        raise CylsfmError(f"{path}: not found") from None
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise CylsfmError(f"{path}: not the points of cylsfm odometry ({exc})") from None
    xyz, rgb, frame, point, uv = (got[k] for k in ("xyz", "rgb", "frame", "point", "uv"))
    n, p = len(frame), len(xyz)
    problem = None
    if xyz.shape != (p, 3) or rgb.shape != (p, 3) or point.shape != (n,) or uv.shape != (n, 2):
        problem = "arrays of shapes that do not fit together"
    elif not (np.issubdtype(frame.dtype, np.integer) and np.issubdtype(point.dtype, np.integer)):
        problem = "frame and point indices that are not integers"
    elif n and (frame.min() < 0 or frame.max() >= frames or point.min() < 0 or point.max() >= p):
        problem = f"observations of frames or points that do not exist ({frames} frames, {p} points)"
    elif not (np.isfinite(xyz).all() and np.isfinite(uv).all()):
        problem = "points or keypoints that are not finite"
    elif n and (uv.min() < -0.5 or (uv.max(0) > np.array(size) - 0.5).any()):
        problem = f"keypoints outside the {size[0]}x{size[1]} frames"
    if problem:
        raise CylsfmError(f"{path}: {problem}")
    return SparsePoints(
        xyz.astype(np.float64), rgb.astype(np.uint8), frame.astype(np.int64), point.astype(np.int64),
        uv.astype(np.float64), str(got["unit"]),
    )  # fmt: skip
