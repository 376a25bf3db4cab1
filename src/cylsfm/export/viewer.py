"""``cylsfm export viewer``: a self-contained web page to look around a panorama's 3D reconstruction.

``OUT_DIR`` gets ``index.html``, ``viewer.js`` (drag to look around, scroll to move, D or the button to
switch between colour and depth), ``scene.js`` (the mesh of :func:`~cylsfm.export.mesh.build_mesh` and the
trajectory, as base64 arrays) and the three.js build the page renders with (``three.min.js``, r158, the
last release with a build that loads from ``file://``; its MIT licence as ``three-LICENSE.txt``). Nothing is
fetched: the page opens from the folder in any browser with WebGL, without a server.

A trajectory (a TUM file, e.g. ``cylsfm odometry``'s) is drawn relative to its first pose, i.e. as if the
panorama was taken at the first frame; its unit must match the depth's (metres with metres).
"""

from __future__ import annotations

import base64
import html
import json
import os
from importlib import resources
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes, atomic_write_text
from ..data.io import read_tum
from ..errors import InputError
from .colorize import colorize_depth
from .mesh import MAX_RATIO, build_mesh
from .scene import Scene

__all__ = ["ASSETS", "export_viewer"]

#: Files copied from the package into every viewer folder.
ASSETS = ("viewer.js", "three.min.js", "three-LICENSE.txt")


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(
        np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<")).tobytes()
    ).decode()


def _trajectory(path: str | os.PathLike[str]) -> np.ndarray:
    """Positions ``float32 [N,3]`` of a TUM trajectory, in the frame of its first pose."""
    _, poses = read_tum(path)
    if not len(poses):
        raise InputError(f"{path}: the trajectory has no poses")
    first = np.linalg.inv(poses[0])
    return np.stack([(first @ p)[:3, 3] for p in poses]).astype(np.float32)


def export_viewer(
    scene: Scene,
    out: str | os.PathLike[str],
    max_ratio: float = MAX_RATIO,
    trajectory: str | os.PathLike[str] | None = None,
    title: str | None = None,
) -> Path:
    """Write the viewer of ``scene`` into the folder ``out``; returns its ``index.html``."""
    mesh = build_mesh(scene, max_ratio)
    depth_rgb = colorize_depth(scene.depth).reshape(-1, 3)
    flat = mesh.pixels[:, 1] * scene.camera.width + mesh.pixels[:, 0]
    scale = float(np.median(np.linalg.norm(mesh.vertices, axis=1))) if len(mesh.vertices) else 1.0
    data = {
        "positions": _b64(mesh.vertices.astype(np.float32)),
        "colours": _b64(mesh.colours.astype(np.uint8)),
        "depthColours": _b64(depth_rgb[flat].astype(np.uint8)),
        "indices": _b64(mesh.faces.astype(np.uint32)),
        "trajectory": _b64(_trajectory(trajectory)) if trajectory is not None else None,
        "scale": scale,
        "info": f"{len(mesh.vertices)} vertices, {len(mesh.faces)} triangles; scale: {scene.scale_note}",
    }
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    assets = resources.files("cylsfm.export") / "assets"
    for name in ASSETS:
        atomic_write_bytes(folder / name, (assets / name).read_bytes())
    atomic_write_text(folder / "scene.js", "window.CYLSFM_SCENE = " + json.dumps(data) + ";\n")
    page = (assets / "viewer.html").read_text(encoding="utf-8")
    page = page.replace("__TITLE__", html.escape(title or "panorama"))
    atomic_write_text(folder / "index.html", page)
    return folder / "index.html"
