"""The bundle adjustment's sparse points as files: ``OUT/points.ply`` (the coloured points, for any
viewer) and ``OUT/points.npz`` (the points with their tracks, for the exports, training and other tools;
its arrays are described, and read, in :mod:`cylsfm.data.points`).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .._version import __version__
from ..atomic import atomic_write_bytes
from ..data.points import SparsePoints, read_points

__all__ = ["SparsePoints", "read_points", "write_points"]


def write_points(
    out: Path, points: np.ndarray, colours: np.ndarray, tracks: np.ndarray, unit: str
) -> SparsePoints:
    """Write ``out/points.ply`` and ``out/points.npz`` atomically: ``points [P,3]`` (the trajectory's world
    and ``unit``), ``colours uint8 [P,3]``, ``tracks [N,4]`` (frame, point, u, v); returns what it wrote."""
    from ..export.mesh import Mesh, write_ply

    xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(colours, dtype=np.uint8).reshape(-1, 3)
    cloud = Mesh(xyz.astype(np.float32), rgb, np.zeros((0, 3), np.int32), np.zeros((len(xyz), 2), np.int64))
    comments = [
        f"cylsfm {__version__} bundle adjustment: triangulated points",
        f"world: the first frame's camera axes (x right, y down, z forward); unit: {unit}",
    ]
    write_ply(cloud, out / "points.ply", comments, points=True)
    tracks = np.asarray(tracks, dtype=np.float64).reshape(-1, 4)
    sparse = SparsePoints(
        xyz, rgb, tracks[:, 0].astype(np.int64), tracks[:, 1].astype(np.int64), tracks[:, 2:], unit
    )
    buf = io.BytesIO()
    np.savez(buf, xyz=xyz, rgb=rgb, frame=sparse.frame, point=sparse.point, uv=sparse.uv, unit=np.array(unit))
    atomic_write_bytes(out / "points.npz", buf.getvalue())
    return sparse
