"""Derivatives of the projections, for direct (photometric) alignment.

:func:`projection_jacobian` gives, for every point of a point map, the 2x3 derivative of its pixel
coordinates ``(u, v)`` with respect to the point ``(x, y, z)``: in closed form for the cylindrical and the
pinhole camera, by automatic differentiation for any other model.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import check_shape
from .cameras import Camera, CylindricalCamera, PinholeCamera

__all__ = ["projection_jacobian"]

_EPS = 1e-8


def _per_batch(p: object, ref: Tensor) -> Tensor | float:
    """An intrinsic ready to broadcast against ``[B,H,W]``."""
    if isinstance(p, Tensor):
        return p.to(device=ref.device, dtype=ref.dtype).reshape(-1, 1, 1)
    return float(p)  # type: ignore[arg-type]


def _cylindrical(camera: Camera, points: Tensor) -> Tensor:
    # u = fx atan2(x, z) + cx, v = fy y / r + cy with r^2 = x^2 + z^2
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    r2 = (x * x + z * z).clamp(min=_EPS)
    r = r2.sqrt()
    fx, fy = _per_batch(camera.fx, x), _per_batch(camera.fy, x)
    zero = torch.zeros_like(x)
    du = torch.stack((fx * z / r2, zero, -fx * x / r2), 1)
    r3 = r2 * r
    dv = torch.stack((-fy * y * x / r3, fy / r, -fy * y * z / r3), 1)
    return torch.stack((du, dv), 1)


def _pinhole(camera: Camera, points: Tensor) -> Tensor:
    # u = fx x / z + cx, v = fy y / z + cy
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    z = torch.where(z.abs() < _EPS, torch.full_like(z, _EPS), z)
    fx, fy = _per_batch(camera.fx, x), _per_batch(camera.fy, x)
    zero = torch.zeros_like(x)
    du = torch.stack((fx / z, zero, -fx * x / (z * z)), 1)
    dv = torch.stack((zero, fy / z, -fy * y / (z * z)), 1)
    return torch.stack((du, dv), 1)


def _autograd(camera: Camera, points: Tensor) -> Tensor:
    # Each pixel's projection depends on its own point only, so the gradient of the sum of all u (of all
    # v) is, pixel by pixel, the derivative of that pixel's u (v).
    with torch.enable_grad():
        p = points.detach().requires_grad_(True)
        uv = camera.project(p)
        (du,) = torch.autograd.grad(uv[:, 0].sum(), p, retain_graph=True)
        (dv,) = torch.autograd.grad(uv[:, 1].sum(), p)
    return torch.stack((du, dv), 1)


def projection_jacobian(camera: Camera, points: Tensor) -> Tensor:
    """The derivative of ``camera.project`` at each point.

    Args:
        camera: any camera model.
        points: camera-frame points ``[B,3,H,W]``.

    Returns:
        ``[B,2,3,H,W]``: ``out[b, i, j, y, x] = d uv_i / d p_j`` at ``points[b, :, y, x]`` (pixels per unit
        of the points' length).

    >>> from cylsfm.geometry import CylindricalCamera
    >>> cam = CylindricalCamera.full(628, 100)
    >>> point = torch.tensor([0.0, 0.0, 2.0]).reshape(1, 3, 1, 1)  # straight ahead, 2 away
    >>> projection_jacobian(cam, point)[0, :, :, 0, 0] + 0.0  # a step to the right moves u by fx / 2
    tensor([[49.9747,  0.0000,  0.0000],
            [ 0.0000, 25.0000,  0.0000]])
    """
    check_shape(points, "B,3,H,W", "points")
    if isinstance(camera, CylindricalCamera):
        return _cylindrical(camera, points)
    if isinstance(camera, PinholeCamera):
        return _pinhole(camera, points)
    return _autograd(camera, points)
