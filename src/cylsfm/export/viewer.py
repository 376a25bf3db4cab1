"""``cylsfm export viewer``: a self-contained web page to look around a panorama's 3D reconstruction.

``OUT_DIR`` gets ``index.html``, ``viewer.js`` (drag to look around, scroll to move, D or the button to
switch between colour and depth), ``scene.js`` (the mesh, textures and trajectory as base64 data) and the
three.js build the page renders with (``three.min.js``, r158, the last release with a build that loads from
``file://``; its MIT licence as ``three-LICENSE.txt``). Nothing is fetched: the page opens from the folder
in any browser with WebGL, without a server.

What the page shows:

- The mesh of :func:`~cylsfm.export.mesh.build_mesh` at a density chosen by a vertex budget, not by the
  network's size (:meth:`~cylsfm.export.scene.Scene.within`: the depth upsampled guided by the panorama's
  colours), its seam's column split so that the texture does not jump across it.
- Textured with the input panorama at its own resolution (up to ``texture_width``, JPEG), not with the
  network's small input.
- Behind it, a far cylinder with the same texture and caps above and below (the panorama's top and bottom
  rows drawn to the axis): where triangles were cut at depth jumps, or above and below the cylinder's field
  of view, the panorama shows instead of an empty black background.
- It opens where the camera stood, looking at the panorama's centre column.

A trajectory (a TUM file, e.g. ``cylsfm odometry``'s) is drawn relative to its first pose, i.e. as if the
panorama was taken at the first frame; its unit must match the depth's (metres with metres).
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
from importlib import resources
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes, atomic_write_text
from ..data.io import read_tum
from ..errors import InputError
from ..geometry import CylindricalCamera
from .colorize import colorize_depth
from .mesh import MAX_RATIO, build_mesh
from .scene import Scene

__all__ = ["ASSETS", "TEXTURE_WIDTH", "VERTICES", "export_viewer"]

#: Default vertex budget of the mesh (a 1024x256 panorama's pixels).
VERTICES = 262_144
#: Default largest width of the colour texture (every WebGL device takes 4096).
TEXTURE_WIDTH = 4096

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


def _data_url(image: np.ndarray, fmt: str) -> str:
    """``uint8 [H,W,3]`` as a ``data:`` URL (a JPEG or PNG file; WebGL takes a data URL's image even from a
    page opened as ``file://``, unlike a file next to it)."""
    from PIL import Image

    buf = io.BytesIO()
    options = {"quality": 92} if fmt == "jpeg" else {}
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format=fmt.upper(), **options)
    return f"data:image/{fmt};base64," + base64.b64encode(buf.getvalue()).decode()


def _background(camera: CylindricalCamera, radius: float, segments: int = 256) -> dict[str, str]:
    """A cylinder of ``radius`` about the camera's vertical axis over the panorama's field of view, with
    caps to the axis above and below, texture coordinates into the panorama (``s`` right, ``t`` down, the
    caps taking its first and last rows): positions, uv and triangles as base64 arrays."""
    w, h = camera.size
    x = np.arange(segments + 1) * (w / segments) - 0.5  # continuous pixel columns, the seam's twice
    theta = (x - float(camera.cx)) / float(camera.fx)
    s = (x + 0.5) / w
    edges = (np.array([-0.5, h - 0.5]) - float(camera.cy)) / float(camera.fy)  # h of the top and bottom
    positions, uv, faces = [], [], []

    def ring(hh: float, t: float) -> int:
        start = sum(len(p) for p in positions)
        positions.append(radius * np.stack([np.sin(theta), np.full_like(theta, hh), np.cos(theta)], -1))
        uv.append(np.stack([s, np.full_like(s, t)], -1))
        return start

    k = np.arange(segments)
    top, bottom = ring(edges[0], 0.0), ring(edges[1], 1.0)
    faces += [
        np.stack([top + k, bottom + k, top + k + 1], -1),
        np.stack([top + k + 1, bottom + k, bottom + k + 1], -1),
    ]
    for hh, t, flip in ((edges[0], 0.5 / h, False), (edges[1], 1 - 0.5 / h, True)):
        rim = ring(hh, t)
        centre = sum(len(p) for p in positions)
        mid = s[:-1] + 0.5 / segments
        positions.append(
            np.stack([np.zeros(segments), np.full(segments, radius * hh), np.zeros(segments)], -1)
        )
        uv.append(np.stack([mid, np.full(segments, t)], -1))
        fan = np.stack([rim + k, centre + k, rim + k + 1], -1)
        faces.append(fan[:, ::-1] if flip else fan)
    return {
        "positions": _b64(np.concatenate(positions).astype(np.float32)),
        "uv": _b64(np.concatenate(uv).astype(np.float32)),
        "indices": _b64(np.concatenate(faces).astype(np.uint32)),
    }


def export_viewer(
    scene: Scene,
    out: str | os.PathLike[str],
    max_ratio: float = MAX_RATIO,
    trajectory: str | os.PathLike[str] | None = None,
    title: str | None = None,
    vertices: int = VERTICES,
    texture_width: int = TEXTURE_WIDTH,
) -> Path:
    """Write the viewer of ``scene`` into the folder ``out``; returns its ``index.html``.

    ``vertices``: the mesh's vertex budget (:meth:`Scene.within`); ``texture_width``: the largest width of
    the colour texture (the original panorama's width when smaller)."""
    if texture_width < 8:
        raise InputError(f"the texture width must be at least 8, got {texture_width}")
    dense = scene.within(vertices)
    mesh = build_mesh(dense, max_ratio, split_seam=True)
    w, h = dense.camera.size
    uv = (mesh.pixels + 0.5) / np.array([w, h], dtype=np.float64)
    texture, _ = scene.colour_at_width(min(texture_width, scene.full_width))
    norms = np.linalg.norm(mesh.vertices, axis=1)
    scale = float(np.median(norms)) if len(norms) else 1.0
    radius = 2.0 * float(norms.max()) if len(norms) else 10.0
    data = {
        "positions": _b64(mesh.vertices.astype(np.float32)),
        "uv": _b64(uv.astype(np.float32)),
        "indices": _b64(mesh.faces.astype(np.uint32)),
        "texture": _data_url(texture, "jpeg"),
        "depthTexture": _data_url(colorize_depth(dense.depth), "png"),
        "background": _background(dense.camera, radius),
        "trajectory": _b64(_trajectory(trajectory)) if trajectory is not None else None,
        "scale": scale,
        "far": 4.0 * radius,
        "info": (
            f"{len(mesh.vertices)} vertices ({w}x{h}), {len(mesh.faces)} triangles, texture "
            f"{texture.shape[1]}x{texture.shape[0]}; scale: {scene.scale_note}"
        ),
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
