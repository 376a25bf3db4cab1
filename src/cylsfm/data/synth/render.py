"""Rendering a frame: rays of the target camera, cast into the scene, shaded and anti-aliased.

Frames are ray cast directly in the target projection (cylindrical, equirectangular or pinhole),
anti-aliased by supersampling, with the true depth of every pixel (the projection's depth; 0 for sky).
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from ...geometry import Camera, CylindricalCamera, EquirectangularCamera, PinholeCamera
from .raycast import cast
from .shading import shade
from .town import StreetScene

__all__ = ["make_camera", "render_frame"]


def make_camera(
    projection: str, width: int, height: int, vfov_h: float = 1.0, pinhole_fov: float = 90.0
) -> Camera:
    """The camera of a generated dataset for ``projection`` in cylindrical | equirect | pinhole.

    Raises:
        InputError: for an unknown ``projection``.
    """
    if projection == "cylindrical":
        return CylindricalCamera.full(width, height, vfov_h)
    if projection in ("equirect", "equirectangular"):
        return EquirectangularCamera.full(width, height)
    if projection == "pinhole":
        return PinholeCamera.from_fov(width, height, pinhole_fov)
    raise InputError(f"unknown projection {projection!r} (expected cylindrical, equirect or pinhole)")


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


_RAY_CACHE: dict[tuple, np.ndarray] = {}  # the rays of the last camera (one camera a process)


def render_frame(
    scene: StreetScene, frame: int, camera: Camera, supersample: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Render ``frame`` of ``scene``'s ride: ``(image uint8 [H,W,3], depth float32 [H,W])``.

    Depth is the camera model's depth of the surface seen at each pixel centre (cylindrical: horizontal
    distance; pinhole: z; equirectangular: range), in metres, 0 for the sky. ``supersample`` overrides the
    scene's anti-aliasing (see :class:`~cylsfm.data.synth.SynthConfig`).
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
    t, obj, face = cast(prisms, origin, dirs)
    finite = np.isfinite(t)
    pts = origin.astype(np.float32) + np.where(finite, t, 0)[:, None] * dirs
    h, w = camera.height, camera.width
    shaded = len(rays) if s <= 1 else len(rays) - h * w  # the grid pattern does not shade the centres
    pixel_angle = scene.config.texture_filter / float(camera.fx)
    colour = shade(
        scene, prisms, pts[:shaded], dirs[:shaded], t[:shaded], obj[:shaded], face[:shaded], pixel_angle
    )
    image = _resolve(colour, h, w, s)
    image = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    t_c = t[-h * w :]
    depth = np.where(np.isfinite(t_c), t_c, 0.0).reshape(h, w).astype(np.float32)
    return image, depth
