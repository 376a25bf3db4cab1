"""Pinhole views that share a centre (a cube map, a multi-camera rig, SYNTHIA's four 90-degree views)
stitched into one cylindrical panorama: colour blended across the seams, depth converted to cylindrical
depth.

Each :class:`View` is a camera turned within the rig (``rotation``: its axes in the rig's frame, the frame of
the panorama). Colour: every view is resampled into the cylinder (:class:`~cylsfm.data.convert.Resampler`,
supersampled and area-averaged) together with a feathering weight that falls linearly from 1 at the view's
centre to 0 at its border, and the views are averaged with those weights, so that seams cross-fade.
Depth: each panorama pixel takes the view in which it lies most centrally; the view's depth along its
optical axis ``z`` is interpolated at the pixel's ray (bilinearly in inverse depth, exact on planes;
across an occlusion edge only from the neighbours on the nearest pixel's side, so that no depth is
invented between a foreground and its background) and converted to cylindrical depth ``d = z / (R^T r)_z`` for the unit cylinder ray ``r``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from ..geometry import Camera, CylindricalCamera, PinholeCamera
from .convert import Resampler

__all__ = ["Stitcher", "View", "view_rotation"]

#: Of four neighbours, only those within this ratio of the nearest one's depth are interpolated ...
EDGE_RATIO = 1.05
#: ... unless they lie on one plane: inverse depth affine in the pixel coordinates, its second differences
#: within this fraction of the largest inverse depth (a plane seen at a grazing angle; 1% allows for depth
#: stored in whole centimetres).
PLANE_TOL = 0.01


def view_rotation(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """A view's axes in the rig frame, ``float64 [3,3]`` (``p_rig = R p_view``).

    ``yaw``: turned about the vertical axis towards the right (+x; the panorama's azimuth of the view's
    centre), then ``pitch`` up, then ``roll`` about its optical axis (clockwise as seen from behind).

    >>> np.round(view_rotation(90.0) @ [0.0, 0.0, 1.0], 6)  # a view turned right looks along +x
    array([1., 0., 0.])
    """
    a, b, c = (math.radians(v) for v in (yaw_deg, pitch_deg, roll_deg))
    ry = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return ry @ rx @ rz


@dataclass(frozen=True)
class View:
    """One camera of a rig: its name, intrinsics (pinhole) and axes in the rig frame (``p_rig = R p_view``)."""

    name: str
    camera: Camera
    rotation: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise InputError(f"view {self.name}: rotation must be a proper 3x3 rotation matrix")
        if not isinstance(self.camera, PinholeCamera):
            raise InputError(
                f"view {self.name}: the views of a rig must be pinhole cameras, got {self.camera.model}"
            )


def _feather(camera: Camera, uv: torch.Tensor) -> torch.Tensor:
    """Weight ``[...]`` of pixel positions ``uv [2,...]``: 1 at the centre, falling linearly to 0 half a pixel
    beyond the image's outer edge (so that a pixel on the edge, where two abutting views meet, still
    counts)."""
    w, h = camera.size
    wu = 1 - (2 * uv[0] - (w - 1)).abs() / (w + 1)
    wv = 1 - (2 * uv[1] - (h - 1)).abs() / (h + 1)
    return (wu.clamp(min=0) * wv.clamp(min=0)).float()


def _padded(camera: Camera) -> Camera:
    """The camera of its image padded by one pixel on every side (edge pixels repeated)."""
    return replace(
        camera, width=camera.width + 2, height=camera.height + 2, cx=camera.cx + 1, cy=camera.cy + 1
    )


class Stitcher:
    """Stitch the frames of a rig of views into panoramas of ``dst`` (maps computed once).

    Args:
        views: the rig's views (at least one).
        dst: the cylindrical panorama's camera.

    Attributes:
        coverage: ``bool [H,W]`` panorama pixels that some view sees.
    """

    def __init__(self, views: Sequence[View], dst: CylindricalCamera) -> None:
        if not views:
            raise InputError("a rig needs at least one view")
        self.views, self.dst = list(views), dst
        # each view padded by one repeated pixel: rays up to its outer edge (where abutting views such as
        # cube faces meet) have four neighbours to sample
        self.colour_maps = [
            Resampler(_padded(v.camera), dst, wrap=False, rotation=v.rotation) for v in self.views
        ]
        # each padded view's feathering weight, in the view's own pixel coordinates
        self.weights = [
            _feather(v.camera, _padded(v.camera).pixel_grid(1, dtype=torch.float64)[0] - 1)
            for v in self.views
        ]
        rays = dst.rays(dst.pixel_grid(1, dtype=torch.float64))[0]  # [3,H,W] unit-cylinder rays
        best = torch.zeros(dst.height, dst.width)
        self.choice = torch.full((dst.height, dst.width), -1, dtype=torch.int64)
        self.depth_maps: list[tuple[torch.Tensor, torch.Tensor]] = []
        for i, v in enumerate(self.views):
            turned = torch.einsum("ji,jhw->ihw", torch.as_tensor(v.rotation, dtype=torch.float64), rays)
            uv = v.camera.project(turned[None])[0]
            weight = torch.where(turned[2] > 1e-6, _feather(v.camera, uv), torch.zeros(()))
            self.depth_maps.append((uv, turned[2]))
            take = weight > best
            self.choice[take], best[take] = i, weight[take]
        self.coverage = (self.choice >= 0).numpy()

    def colour(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """The views' ``uint8 [h,w,3]`` images (in the order of ``views``) -> ``uint8 [H,W,3]`` panorama
        (black where no view sees)."""
        self._check(images, "image")
        num = torch.zeros(3, self.dst.height, self.dst.width)
        den = torch.zeros(self.dst.height, self.dst.width)
        for v, image, resample, weight in zip(
            self.views, images, self.colour_maps, self.weights, strict=True
        ):
            if image.ndim != 3 or image.shape[2] != 3:
                raise InputError(f"view {v.name}: an image must be [H,W,3], got {image.shape}")
            rgb = torch.from_numpy(np.array(image, dtype=np.float32)).permute(2, 0, 1)[None]
            rgb = F.pad(rgb, (1, 1, 1, 1), mode="replicate")[0]
            src = torch.cat([rgb * weight, weight[None]])[None]
            with torch.inference_mode():
                out = resample(src)[0]
            num += out[:3]
            den += out[3]
        colour = torch.where(den > 1e-6, num / den.clamp(min=1e-6), torch.zeros(()))
        return colour.clamp(0, 255).round().to(torch.uint8).permute(1, 2, 0).numpy()

    def depth(self, depths: Sequence[np.ndarray]) -> np.ndarray:
        """The views' depth along their optical axes ``[h,w]`` (metres; 0, negative or non-finite:
        unknown) -> cylindrical depth ``float32 [H,W]`` (0: unknown)."""
        self._check(depths, "depth map")
        out = torch.zeros(self.dst.height, self.dst.width, dtype=torch.float64)
        for i, (v, z) in enumerate(zip(self.views, depths, strict=True)):
            if z.ndim != 2:
                raise InputError(f"view {v.name}: a depth map must be [H,W], got {z.shape}")
            mine = self.choice == i
            if not bool(mine.any()):
                continue
            uv, axis = self.depth_maps[i]
            z_at = _sample_depth(torch.from_numpy(np.asarray(z, dtype=np.float64)), uv[:, mine])
            out[mine] = z_at / axis[mine]
        return out.float().numpy()

    def _check(self, items: Sequence[np.ndarray], what: str) -> None:
        if len(items) != len(self.views):
            raise InputError(f"expected one {what} for each of the {len(self.views)} views, got {len(items)}")
        for v, item in zip(self.views, items, strict=True):
            w, h = v.camera.size
            if item.shape[:2] != (h, w):
                raise InputError(
                    f"view {v.name}: {what} is {item.shape[1]}x{item.shape[0]}, the camera {w}x{h}"
                )


def _gather(z: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``z[y, x]`` with 0 outside the image."""
    h, w = z.shape
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return torch.where(ok, z[y.clamp(0, h - 1), x.clamp(0, w - 1)], torch.zeros(()))


def _one_plane(block: torch.Tensor) -> torch.Tensor:
    """Whether the centre cell of a 4x4 block of depths ``[4,4,N]`` lies on one plane: its twist (the
    bilinear term, 0 for inverse depth affine in the pixel coordinates) and, in one of the four 3x3 blocks
    around it, every second difference of inverse depth within :data:`PLANE_TOL` of the largest value."""
    inv = 1 / block.clamp(min=1e-12)
    twist = (inv[1, 1] + inv[2, 2] - inv[1, 2] - inv[2, 1]).abs()
    out = (block[1:3, 1:3] > 0).all(0).all(0) & (twist <= PLANE_TOL * inv[1:3, 1:3].amax((0, 1)))
    side = torch.zeros_like(out)
    for oy in (0, 1):
        for ox in (0, 1):
            b, i = block[oy : oy + 3, ox : ox + 3], inv[oy : oy + 3, ox : ox + 3]
            d2x = (i[:, 0] - 2 * i[:, 1] + i[:, 2]).abs().amax(0)
            d2y = (i[0] - 2 * i[1] + i[2]).abs().amax(0)
            tol = PLANE_TOL * i.amax((0, 1))
            side |= (b > 0).all(0).all(0) & (d2x <= tol) & (d2y <= tol)
    return out & side


def _side_plane(z: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse depth at ``(u, v)`` from a plane through a 3x3 block of pixels containing the nearest pixel
    (one lying on a single plane, e.g. on the nearest pixel's side of an occlusion edge): ``(found [N],
    inverse depth [N])``."""
    nx, ny = u.round().long(), v.round().long()
    found = torch.zeros(u.shape, dtype=torch.bool)
    value = torch.zeros_like(u)
    for oy in (-1, 0, 1):
        for ox in (-1, 0, 1):
            cx, cy = nx + ox, ny + oy  # the block's centre
            b = torch.stack(
                [torch.stack([_gather(z, cx + dx, cy + dy) for dx in (-1, 0, 1)]) for dy in (-1, 0, 1)]
            )
            i = 1 / b.clamp(min=1e-12)
            tol = PLANE_TOL * i.amax((0, 1))
            flat = (b > 0).all(0).all(0)
            flat &= (i[:, 0] - 2 * i[:, 1] + i[:, 2]).abs().amax(0) <= tol
            flat &= (i[0] - 2 * i[1] + i[2]).abs().amax(0) <= tol
            flat &= (i[0, 0] + i[2, 2] - i[0, 2] - i[2, 0]).abs() <= 2 * tol
            pred = i[1, 1] + (i[1, 2] - i[1, 0]) / 2 * (u - cx) + (i[2, 1] - i[0, 1]) / 2 * (v - cy)
            take = flat & ~found & (pred > 0)
            value = torch.where(take, pred, value)
            found |= take
    return found, value


def _sample_depth(z: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """``z [h,w]`` at pixel positions ``uv [2,N]``: bilinear in inverse depth over the four neighbours when
    they lie on one plane (:func:`_one_plane`; exact there, also at grazing angles); else (an occlusion edge
    between them) from the plane of a 3x3 block around the nearest pixel (:func:`_side_plane`); else over
    those of the four on the nearest pixel's surface (within :data:`EDGE_RATIO` of its depth), weights
    renormalised; 0 where the nearest pixel is unknown or outside."""
    h, w = z.shape
    z = torch.where(torch.isfinite(z) & (z > 0), z, torch.zeros(()))
    u, v = uv[0], uv[1]
    inside = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    nearest = torch.where(inside, _gather(z, u.round().long(), v.round().long()), torch.zeros(()))
    x0, y0 = u.floor().long(), v.floor().long()
    fx, fy = u - x0, v - y0
    block = torch.stack(
        [torch.stack([_gather(z, x0 + dx, y0 + dy) for dx in (-1, 0, 1, 2)]) for dy in (-1, 0, 1, 2)]
    )
    inv = 1 / block.clamp(min=1e-12)
    plane = _one_plane(block)
    inverse = torch.zeros_like(u)
    total = torch.zeros_like(u)
    jump = torch.zeros(u.shape, dtype=torch.bool)
    for dy in (0, 1):
        for dx in (0, 1):
            c = block[1 + dy, 1 + dx]
            same = (c > 0) & (c <= EDGE_RATIO * nearest) & (nearest <= EDGE_RATIO * c)
            jump |= ~same
            weight = (fx if dx else 1 - fx) * (fy if dy else 1 - fy) * (same | plane)
            inverse += weight * inv[1 + dy, 1 + dx]
            total += weight
    side, side_inverse = _side_plane(z, u, v)
    edge = ~plane & jump & side  # a crease (no jump) is interpolated across, an occlusion edge is not
    inverse = torch.where(edge, side_inverse, inverse)
    total = torch.where(edge, torch.ones(()), total)
    # the nearest pixel is one of the four and on its own surface: total > 0 wherever it is known
    return torch.where((nearest > 0) & (total > 0), total / inverse.clamp(min=1e-30), torch.zeros(()))
