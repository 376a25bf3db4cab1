"""A panorama's depth as a coloured triangle mesh or point cloud (PLY, written with ``plyfile``).

Every pixel with known depth is a vertex at ``camera.unproject(depth)`` (camera axes: x right, y down,
z forward; the camera at the origin), coloured by its pixel. Each cell of four neighbouring pixels gives two
triangles, including the cells between the last column and the first: the 360-degree seam is closed.
Triangles are left out where a vertex is unknown (sky, invalid depth) and where they would bridge a depth
discontinuity: the largest of a triangle's three depths more than ``max_ratio`` times the smallest (a
foreground edge in front of its background; such triangles are long slivers along the viewing rays).
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..atomic import atomic_write_bytes
from ..errors import InputError
from .scene import Scene

__all__ = ["Mesh", "build_mesh", "write_ply"]

#: Default largest ratio between the depths of one triangle's corners.
MAX_RATIO = 1.2


@dataclass(frozen=True)
class Mesh:
    """Vertices ``float32 [N,3]`` (camera frame, the scene's unit), colours ``uint8 [N,3]``, triangles
    ``int32 [M,3]`` (vertex indices), and for each vertex its pixel ``int64 [N,2]`` as ``(u, v)``."""

    vertices: np.ndarray
    colours: np.ndarray
    faces: np.ndarray
    pixels: np.ndarray


def build_mesh(
    scene: Scene, max_ratio: float = MAX_RATIO, max_depth: float | None = None, split_seam: bool = False
) -> Mesh:
    """The mesh of ``scene`` (see the module docstring); ``max_depth`` also leaves out farther pixels.

    ``split_seam``: the first column's vertices once more as a column ``u = W`` after the last, which the
    seam's cells use instead of wrapping to ``u = 0`` (for a texture, whose coordinate must not jump back
    across the seam)."""
    if not max_ratio > 1:
        raise InputError(f"max_ratio must be above 1, got {max_ratio}")
    cam, depth = scene.camera, scene.depth.astype(np.float32)
    h, w = depth.shape
    known = np.isfinite(depth) & (depth > 0)
    if max_depth is not None:
        known &= depth <= max_depth
    points = cam.unproject(torch.from_numpy(np.where(known, depth, 0))[None, None])[0].permute(1, 2, 0)
    image = scene.image
    cols = w
    if split_seam:  # the first column again after the last
        depth, known = np.concatenate([depth, depth[:, :1]], 1), np.concatenate([known, known[:, :1]], 1)
        points, image = torch.cat([points, points[:, :1]], 1), np.concatenate([image, image[:, :1]], 1)
        cols = w + 1
    points = points.reshape(-1, 3).numpy()
    index = np.full(h * cols, -1, dtype=np.int64)
    flat_known = known.reshape(-1)
    index[flat_known] = np.arange(int(flat_known.sum()))
    # the cell (v, u) -- (v + 1, u + 1) with u + 1 wrapping to 0 (or the seam's column): the seam's cells too
    v, u = np.meshgrid(np.arange(h - 1), np.arange(w), indexing="ij")
    right = u + 1 if split_seam else (u + 1) % w
    a, b = v * cols + u, v * cols + right
    c, d = (v + 1) * cols + u, (v + 1) * cols + right
    tris = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    flat_depth = depth.reshape(-1)
    ok = flat_known[tris].all(1)
    corner = flat_depth[tris]
    ok &= corner.max(1) <= max_ratio * np.maximum(corner.min(1), 1e-12)
    faces = index[tris[ok]].astype(np.int32)
    vv, uu = np.divmod(np.nonzero(flat_known)[0], cols)
    return Mesh(
        points[flat_known].astype(np.float32),
        image.reshape(-1, 3)[flat_known],
        faces,
        np.stack([uu, vv], -1),
    )


def write_ply(mesh: Mesh, path: str | os.PathLike[str], comments: list[str], points: bool = False) -> Path:
    """Write ``mesh`` (or only its coloured vertices, ``points``) as binary PLY, atomically."""
    from plyfile import PlyData, PlyElement

    vertex = np.empty(
        len(mesh.vertices),
        dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    for i, name in enumerate("xyz"):
        vertex[name] = mesh.vertices[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        vertex[name] = mesh.colours[:, i]
    elements = [PlyElement.describe(vertex, "vertex")]
    if not points:
        face = np.empty(len(mesh.faces), dtype=[("vertex_indices", "i4", (3,))])
        face["vertex_indices"] = mesh.faces
        elements.append(PlyElement.describe(face, "face"))

    buf = io.BytesIO()
    PlyData(elements, text=False, comments=comments).write(buf)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)
