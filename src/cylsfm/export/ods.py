"""Omni-directional stereo (ODS): the left and right eye panoramas a VR headset shows, rendered from a
panorama and its depth.

In ODS every column's ray starts on the viewing circle of radius ``r = IPD / 2`` and is tangent to it: the
eye looking at azimuth ``theta`` sits at ``s r (-cos theta, 0, sin theta)`` (``s = +1`` left, ``-1``
right: beside the viewing direction, x right, z forward). A point at horizontal distance ``rho`` and
azimuth ``phi`` is seen by eye ``s`` at azimuth ``theta' = phi + asin(s r / rho)``, at horizontal distance
``t = sqrt(rho^2 - r^2)`` along the ray, and at height ``y``; so at ``camera.project((t sin theta', y,
t cos theta'))`` of the output camera (cylindrical or equirectangular). The two eyes' azimuths differ by
the disparity ``2 asin(r / rho)``.

Rendering splats every source pixel's depth (2x2 sub-pixels, so that stretched surfaces leave no gaps)
into each eye with a z-buffer (the nearest point wins); each eye pixel then takes the source's colour where
its ray meets that depth, sampled bilinearly (so disparities are exact to a fraction of a pixel). What the
source does not show (disocclusions behind a foreground edge: the source sees something nearer there) is
filled along the row from the farther of its two neighbours, so that a foreground never smears into the
background; rows the source does not reach stay black.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import InputError
from ..geometry import Camera, CylindricalCamera, EquirectangularCamera, sample_image
from .scene import Scene

__all__ = ["anaglyph", "ods_pair", "render_eye", "stereo_layout"]


def _source_points(scene: Scene, sub: int) -> tuple[np.ndarray, np.ndarray]:
    """Points ``[N,3]`` of ``sub x sub`` samples a known pixel (its depth) and their colours ``[N,3]``."""
    cam = scene.camera
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    grid = cam.pixel_grid(1, dtype=torch.float64)[0]  # [2,H,W]
    pts, cols = [], []
    known = scene.depth > 0
    for oy in offs:
        for ox in offs:
            uv = grid + torch.tensor([ox, oy], dtype=torch.float64).view(2, 1, 1)
            rays = cam.rays(uv[None])[0]  # unit-cylinder rays: point = depth * ray
            p = (rays * torch.from_numpy(scene.depth.astype(np.float64))[None]).permute(1, 2, 0)
            pts.append(p.numpy()[known])
            cols.append(scene.image[known])
    return np.concatenate(pts), np.concatenate(cols)


def render_eye(
    scene: Scene,
    out: Camera,
    ipd: float,
    eye: str,
    sub: int = 2,
    fill: bool = True,
    points: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One eye's ODS panorama of ``scene`` in camera ``out`` (full cylindrical or equirectangular).

    Args:
        ipd: the distance between the eyes, in the scene's depth unit.
        eye: ``"left"`` or ``"right"``.
        sub: sub-pixel samples per source pixel and axis.
        fill: fill disocclusions from the background.
        points: the scene's sub-sampled points and colours when already computed (both eyes share them).

    Returns:
        ``(image uint8 [H,W,3], depth float32 [H,W])`` (depth: horizontal distance along the eye's ray;
        0 where nothing is seen).
    """
    if eye not in ("left", "right"):
        raise InputError(f"eye must be left or right, got {eye!r}")
    if not isinstance(out, CylindricalCamera | EquirectangularCamera) or not out.wraps:
        raise InputError("ODS output must be a full 360-degree cylindrical or equirectangular camera")
    r = ipd / 2
    s = 1.0 if eye == "left" else -1.0
    pts, cols = points if points is not None else _source_points(scene, sub)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    rho = np.hypot(x, z)
    seen = rho > r * 1.0001  # inside the viewing circle nothing is seen by a tangent ray
    x, y, z, rho, cols = x[seen], y[seen], z[seen], rho[seen], cols[seen]
    theta = np.arctan2(x, z) + np.arcsin(s * r / rho)
    t = np.sqrt(rho**2 - r**2)
    q = np.stack([t * np.sin(theta), y, t * np.cos(theta)])
    uv = out.project(torch.from_numpy(q).reshape(1, 3, -1, 1))[0, :, :, 0].numpy()
    u = np.mod(np.round(uv[0]).astype(np.int64), out.width)
    v = np.round(uv[1]).astype(np.int64)
    inside = (v >= 0) & (v < out.height)
    u, v, t, cols = u[inside], v[inside], t[inside], cols[inside]
    flat = v * out.width + u
    order = np.lexsort((t, flat))  # by pixel, nearest first
    first = np.ones(len(order), dtype=bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    keep = order[first]  # the nearest point of every pixel hit: the z-buffer
    image = np.zeros((out.height * out.width, 3), dtype=np.uint8)
    depth = np.zeros(out.height * out.width, dtype=np.float32)
    image[flat[keep]] = cols[keep]
    depth[flat[keep]] = t[keep]
    image, depth = image.reshape(out.height, out.width, 3), depth.reshape(out.height, out.width)
    if fill:
        image, depth = _fill_from_background(image, depth)
    return _resample_colour(scene, out, image, depth, s * r), depth


def _resample_colour(
    scene: Scene, out: Camera, image: np.ndarray, depth: np.ndarray, offset: float
) -> np.ndarray:
    """Each eye pixel's colour sampled bilinearly from the source where its ray meets the splatted depth
    (sub-pixel exact), kept from the splat where the source sees something nearer there (a disocclusion)."""
    grid = out.pixel_grid(1, dtype=torch.float64)
    rays = out.rays(grid)[0]  # [3,H,W]
    rays = rays / torch.hypot(rays[0], rays[2]).clamp(min=1e-9)  # unit horizontal length
    theta = torch.atan2(rays[0], rays[2])
    t = torch.from_numpy(depth.astype(np.float64))
    origin = torch.stack([-offset * torch.cos(theta), torch.zeros_like(theta), offset * torch.sin(theta)])
    points = origin + t[None] * rays
    src = scene.camera
    uv = src.project(points[None].float())
    colour = torch.from_numpy(scene.image).permute(2, 0, 1)[None].float()
    sampled, valid = sample_image(colour, uv, wrap=True)
    near = torch.from_numpy(scene.depth)[None, None].float()
    seen, _ = sample_image(near, uv.round(), wrap=True)
    rho = torch.hypot(points[0], points[2]).float()
    ok = valid[0, 0] & (t > 0) & ((seen[0, 0] - rho).abs() <= 0.05 * rho)
    out_image = torch.where(ok[None], sampled[0], torch.from_numpy(image).permute(2, 0, 1).float())
    return out_image.clamp(0, 255).round().to(torch.uint8).permute(1, 2, 0).numpy()


def _fill_from_background(image: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill each row's holes (depth 0) from the farther of the nearest known pixels left and right
    (around the seam); rows without any known pixel stay empty."""
    h, w = depth.shape
    image, depth = image.copy(), depth.copy()
    idx = np.arange(3 * w)
    for row in range(h):
        known = np.tile(depth[row] > 0, 3)
        if not known[:w].any() or known[:w].all():
            continue
        left = np.maximum.accumulate(np.where(known, idx, -1))
        right = np.minimum.accumulate(np.where(known, idx, 3 * w)[::-1])[::-1]
        cols = np.arange(w, 2 * w)
        hole = ~known[cols]
        lcol, rcol = left[cols][hole] % w, right[cols][hole] % w
        take = np.where(depth[row, lcol] >= depth[row, rcol], lcol, rcol)
        image[row, cols[hole] - w] = image[row, take]
        depth[row, cols[hole] - w] = depth[row, take]
    return image, depth


def ods_pair(scene: Scene, out: Camera, ipd: float, sub: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(left, right)`` ODS eye images ``uint8 [H,W,3]`` of ``scene`` in camera ``out``."""
    if not (math.isfinite(ipd) and ipd > 0):
        raise InputError(f"ipd must be a positive distance, got {ipd}")
    points = _source_points(scene, sub)
    left = render_eye(scene, out, ipd, "left", sub, points=points)[0]
    return left, render_eye(scene, out, ipd, "right", sub, points=points)[0]


def stereo_layout(left: np.ndarray, right: np.ndarray, layout: str) -> np.ndarray:
    """The pair in one image: ``top-bottom`` (left eye on top, the usual for 360 video) or
    ``side-by-side`` (left eye on the left)."""
    if layout == "top-bottom":
        return np.concatenate([left, right], 0)
    if layout == "side-by-side":
        return np.concatenate([left, right], 1)
    raise InputError(f"layout must be top-bottom or side-by-side, got {layout!r}")


def anaglyph(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """A red-cyan anaglyph: red from the left eye, green and blue from the right."""
    out = right.copy()
    out[..., 0] = left[..., 0]
    return out
