"""A tiny analytic scene: a closed room with a pillar, rendered exactly by ray casting.

Every surface has a smooth multi-frequency colour defined at the world point, so images have gradients
everywhere, and the true depth and pose of every frame are known exactly. It is the scene of the geometry
tests and of the quick self-check; the street benchmark generator is the rest of :mod:`cylsfm.data.synth`.
"""

from __future__ import annotations

import math

import torch

from ...geometry import Camera

__all__ = ["PILLAR_HI", "PILLAR_LO", "ROOM_HI", "ROOM_LO", "make_pose", "render_room"]

ROOM_LO = torch.tensor([-4.0, -2.5, -6.0], dtype=torch.float64)
ROOM_HI = torch.tensor([5.0, 1.6, 7.0], dtype=torch.float64)
PILLAR_LO = torch.tensor([1.2, -2.5, 2.0], dtype=torch.float64)
PILLAR_HI = torch.tensor([2.0, 1.6, 2.8], dtype=torch.float64)


def _texture(points: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """Colour [N,3] of world points [N,3] lying on faces whose normal is along ``axis`` [N] (0, 1, 2)."""
    x, y, z = points.unbind(-1)
    # in-plane coordinates of the face
    a = torch.where(axis == 0, z, x)
    b = torch.where(axis == 1, z, y)
    face = axis.to(points.dtype)
    chans = []
    for c in range(3):
        ph = 1.7 * c + 0.9 * face
        val = (
            0.5
            + 0.18 * torch.sin(1.1 * a + 0.6 * b + ph)
            + 0.12 * torch.sin(2.9 * a - 2.1 * b + 2 * ph)
            + 0.08 * torch.sin(5.3 * b + 1.3 * a - ph)
        )
        chans.append(val)
    return torch.stack(chans, -1).clamp(0, 1)


def _cast(origin: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray parameter ``t`` [N] of the first hit and the hit face's axis [N] for rays ``origin + t dirs``."""
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    # room, from inside: exit through the nearest wall
    t_wall = torch.where(safe > 0, (ROOM_HI - origin) / safe, (ROOM_LO - origin) / safe)
    t_room, ax_room = t_wall.min(-1)
    # pillar, slab method
    t1 = (PILLAR_LO - origin) / safe
    t2 = (PILLAR_HI - origin) / safe
    t_near, ax_near = torch.minimum(t1, t2).max(-1)
    t_far = torch.maximum(t1, t2).min(-1).values
    hit = (t_near <= t_far) & (t_near > 1e-6) & (t_near < t_room)
    t = torch.where(hit, t_near, t_room)
    axis = torch.where(hit, ax_near, ax_room)
    return t, axis


def render_room(camera: Camera, c2w: torch.Tensor, supersample: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Render the room: ``(image [1,3,H,W] float32 in [0,1], depth [1,1,H,W] float32 in the camera's depth)``.

    ``c2w`` is the [4,4] camera-to-world pose. Colours are averaged over ``supersample^2`` rays a pixel.
    """
    c2w = c2w.to(torch.float64)
    rot, origin = c2w[:3, :3], c2w[:3, 3]
    grid = camera.pixel_grid(1, dtype=torch.float64)
    colour = torch.zeros(1, 3, camera.height, camera.width, dtype=torch.float64)
    s = supersample
    for i in range(s):
        for j in range(s):
            off = torch.tensor([(j + 0.5) / s - 0.5, (i + 0.5) / s - 0.5], dtype=torch.float64).view(
                1, 2, 1, 1
            )
            rays = camera.rays(grid + off)  # [1,3,H,W] camera frame, unit depth
            dirs = (rot @ rays.reshape(3, -1)).T
            t, axis = _cast(origin, dirs)
            pts = origin + t.unsqueeze(-1) * dirs
            colour += _texture(pts, axis).T.reshape(1, 3, camera.height, camera.width)
    colour /= s * s
    rays = camera.rays(grid)
    dirs = (rot @ rays.reshape(3, -1)).T
    t, _ = _cast(origin, dirs)
    depth = t.reshape(1, 1, camera.height, camera.width)  # rays have unit depth, so depth == t
    return colour.float(), depth.float()


def make_pose(tx: float, ty: float, tz: float, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> torch.Tensor:
    """Camera-to-world [4,4]: yaw about y, then pitch about x, at (tx, ty, tz)."""
    a, b = math.radians(yaw_deg), math.radians(pitch_deg)
    ry = torch.tensor(
        [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64
    )
    rx = torch.tensor(
        [[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]], dtype=torch.float64
    )
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = ry @ rx
    out[:3, 3] = torch.tensor([tx, ty, tz], dtype=torch.float64)
    return out
