"""Resampling panoramas and photographs into a cylindrical camera.

:func:`to_cylinder` turns an equirectangular 360-degree image (the usual output of 360 cameras), a
cylindrical panorama of another size or vertical field of view, or a pinhole photograph into the
cylindrical panorama of a given :class:`~cylsfm.geometry.CylindricalCamera`: every destination pixel's ray
(``dst_camera.rays``) is projected into the source (``src_camera.project``) and the source is sampled there
bilinearly (:func:`~cylsfm.geometry.sample_image`, wrapping around the seam of a full source panorama).

Anti-aliasing: bilinear sampling alone aliases when the source has many pixels per destination pixel
(a 5760x2880 equirectangular frame into a 512x128 cylinder has about 11 source pixels per destination pixel).
:func:`to_cylinder` therefore

1. samples an integer supersampling of the destination, ``sx x sy`` samples a pixel (the destination camera
   :meth:`~cylsfm.geometry.Camera.resized` to ``(sx W, sy H)``), and averages each block (area average),
   which is exactly the destination's pixel grid;
2. when even that is too sparse (more than ``2 * max_supersample`` source pixels per destination pixel),
   first area-averages the source by an integer factor ``kx x ky``,

so that neighbouring samples lie 1 to 2 (pre-averaged) source pixels apart. The factors come from the ratio
of the focal lengths at the optical centre (``src.fx / dst.fx``, ``src.fy / dst.fy``, pixels per radian
there); away from the centre the true ratio differs (an equirectangular row spans less height near the
top of a cylinder; a pinhole view is denser at its edges), which the 1-2 pixel margin absorbs.

Between full panoramas about one vertical axis (an equirectangular or cylindrical 360-degree source into a
full cylinder) the map is separable, and :class:`Resampler` uses exact box filtering along the rows and
then the columns instead (:mod:`cylsfm.data.separable`): an order of magnitude faster, and exact area
averaging.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError
from ..geometry import Camera, CylindricalCamera, sample_image
from .separable import SeparableMap, separable

__all__ = ["Resampler", "depth_to_camera", "plan_resampling", "to_cylinder"]


def _max_float(p: float | Tensor) -> float:
    return float(p.max()) if isinstance(p, Tensor) else float(p)


def plan_resampling(
    src_camera: Camera, dst_camera: Camera, max_supersample: int = 4
) -> tuple[tuple[int, int], tuple[int, int]]:
    """The anti-aliasing factors :func:`to_cylinder` uses: ``((sx, sy), (kx, ky))``.

    ``r = src.f / dst.f`` is the number of source pixels per destination pixel along an axis (at the
    optical centre). The destination is supersampled ``s = clamp(ceil(r), 1, max_supersample)`` times and
    the source area-averaged ``k = max(1, floor(r / s))`` times, so that samples are ``r / (s k)`` in
    ``[1, 2)`` averaged source pixels apart (when ``r >= 1``; upsampling uses ``s = k = 1``).
    """
    if max_supersample < 1:
        raise InputError(f"max_supersample must be >= 1, got {max_supersample}")
    out_s, out_k = [], []
    for name in ("fx", "fy"):
        r = _max_float(getattr(src_camera, name)) / _max_float(getattr(dst_camera, name))
        s = min(max_supersample, max(1, math.ceil(r - 1e-6)))
        k = max(1, math.floor(r / s + 1e-6))
        out_s.append(s)
        out_k.append(k)
    return (out_s[0], out_s[1]), (out_k[0], out_k[1])


def to_cylinder(
    image: Tensor,
    src_camera: Camera,
    dst_camera: CylindricalCamera,
    wrap: bool | None = None,
    *,
    supersample: int | tuple[int, int] | None = None,
    max_supersample: int = 4,
    return_mask: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Resample ``image`` seen by ``src_camera`` into the cylindrical panorama of ``dst_camera``.

    Both cameras share their centre and axes (x right, y down, z forward): a destination pixel looking
    along ray ``r`` takes the source's colour at ``src_camera.project(r)``.

    Args:
        image: ``[B,C,H,W]`` float source images (any range; colours are averaged linearly) whose size is
            ``src_camera``'s. Integer images are converted to float32.
        src_camera: the source's camera (equirectangular, cylindrical or pinhole; scalar or ``[B]``
            intrinsics).
        dst_camera: the cylindrical camera of the result, size ``W' x H'``.
        wrap: sample across the source's left/right seam; ``None``: when the source covers a full turn
            (``src_camera.wraps``). ``True`` with a source that does not wrap is an error.
        supersample: samples per destination pixel along each axis (an int for both, or ``(sx, sy)``);
            ``None`` chooses them from the focal lengths (:func:`plan_resampling`), and then the source may
            also be area-averaged first. An explicit value never pre-averages the source.
        max_supersample: upper bound of the automatic supersampling per axis.
        return_mask: also return the mask of destination pixels that have a source.

    Returns:
        ``[B,C,H',W']`` in the dtype of ``image`` (float32 for integer input); with ``return_mask``,
        ``(image, mask [B,1,H',W'] bool)``. A destination pixel is valid when at least half of its samples
        have a source (inside the source vertically, horizontally unless it wraps, and in front of a pinhole
        camera); its colour is the mean of those samples. Invalid pixels are 0.
    """
    resampler = Resampler(
        src_camera,
        dst_camera,
        wrap,
        supersample=supersample,
        max_supersample=max_supersample,
        device=image.device,
    )
    out, mask = resampler(image, return_mask=True)
    return (out, mask) if return_mask else out


class Resampler:
    """:func:`to_cylinder` with its sampling map computed once, for many frames of one camera.

    Full panoramas into a full cylinder use the separable box filter (:mod:`cylsfm.data.separable`) unless
    ``supersample`` is given.

    The destination's (supersampled) rays, their projections into the (pre-averaged) source and the
    projectability mask are computed at construction; a call only pre-averages, samples and averages.

    Args:
        src_camera, dst_camera, wrap, supersample, max_supersample: as for :func:`to_cylinder` (``wrap``
            ``None``: when the source covers a full turn).
        device: where the map lives (the images' device).
        rotation: ``[3,3]`` the source camera's axes in the destination's frame (``p_dst = R p_src``), for
            a view turned within a rig (:mod:`cylsfm.data.stitch`); ``None``: the same axes.
    """

    def __init__(
        self,
        src_camera: Camera,
        dst_camera: CylindricalCamera,
        wrap: bool | None = None,
        *,
        supersample: int | tuple[int, int] | None = None,
        max_supersample: int = 4,
        device: torch.device | str = "cpu",
        rotation: Tensor | np.ndarray | None = None,
    ) -> None:
        if not isinstance(dst_camera, CylindricalCamera):
            raise TypeError(f"dst_camera must be a CylindricalCamera, got {type(dst_camera).__name__}")
        if wrap and not src_camera.wraps:
            raise InputError("wrap=True needs a source camera that covers a full turn (fx * 2 pi == width)")
        self.wrap = src_camera.wraps if wrap is None else wrap
        self.src_camera, self.dst_camera = src_camera, dst_camera
        self.separable: SeparableMap | None = None
        turn = None if rotation is None else torch.as_tensor(rotation, dtype=torch.float64).reshape(3, 3)
        if turn is not None and torch.equal(turn, torch.eye(3, dtype=torch.float64)):
            turn = None
        if supersample is None and self.wrap and turn is None and separable(src_camera, dst_camera):
            self.separable = SeparableMap(src_camera, dst_camera)
            return
        if supersample is None:
            (sx, sy), (kx, ky) = plan_resampling(src_camera, dst_camera, max_supersample)
        else:
            sx, sy = (supersample, supersample) if isinstance(supersample, int) else supersample
            kx = ky = 1
            if sx < 1 or sy < 1:
                raise InputError(f"supersample must be >= 1, got {supersample}")
        self.factors = (sx, sy)
        w, h = src_camera.size
        # area pre-average; the resized camera describes the averaged pixels (exact when k divides the size)
        self.averaged = (max(1, h // ky), max(1, w // kx)) if kx > 1 or ky > 1 else None
        cam = src_camera if self.averaged is None else src_camera.resized(self.averaged[1], self.averaged[0])
        big = (
            dst_camera
            if (sx, sy) == (1, 1)
            else dst_camera.resized(dst_camera.width * sx, dst_camera.height * sy)
        )
        rays = big.rays(big.pixel_grid(1, device=device, dtype=torch.float64))
        if turn is not None:  # the destination's rays in the source's axes: R^T r
            rays = torch.einsum("ji,bjhw->bihw", turn.to(device), rays)
        self.uv = cam.project(rays).float()  # [1 or B,2,sy H',sx W'] source pixels
        self.ok = cam.projectable(rays)

    def __call__(self, image: Tensor, return_mask: bool = False) -> Tensor | tuple[Tensor, Tensor]:
        """``image [B,C,H,W]`` (the source camera's size) -> ``[B,C,H',W']`` (and the mask ``[B,1,H',W']``)."""
        h, w = image.shape[-2:]
        if image.dim() != 4 or (w, h) != self.src_camera.size:
            raise InputError(
                f"image must be [B,C,{self.src_camera.height},{self.src_camera.width}], got {tuple(image.shape)}"
            )
        if self.separable is not None:
            out, mask = self.separable(image)
            return (out, mask) if return_mask else out
        out_dtype = image.dtype if image.is_floating_point() else torch.float32
        src = image.float() if out_dtype != torch.float64 else image
        if self.averaged is not None:
            src = F.interpolate(src, size=self.averaged, mode="area")
        with torch.autocast(device_type=src.device.type, enabled=False):
            out, mask = self._sample(src)
        out = out.to(out_dtype)
        return (out, mask) if return_mask else out

    def frames(self, frames: list[np.ndarray]) -> list[np.ndarray]:
        """Decoded ``uint8 [H,W,3]`` frames -> ``uint8 [H',W',3]`` frames (rounded), the fastest way."""
        if self.separable is not None:
            return [self.separable.frame(f) for f in frames]
        batch = torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2)
        with torch.inference_mode():
            out = self(batch.float())
        return list(out.clamp(0, 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy())

    def _sample(self, src: Tensor) -> tuple[Tensor, Tensor]:
        """Sample ``src`` at ``sx x sy`` points per destination pixel and average each pixel's valid samples."""
        sx, sy = self.factors
        b = src.shape[0]
        uv, ok = self.uv.to(src.device), self.ok.to(src.device)
        if uv.shape[0] == 1 and b > 1:
            uv, ok = uv.expand(b, -1, -1, -1), ok.expand(b, -1, -1, -1)
        sampled, valid = sample_image(src, uv, self.wrap)
        valid = valid & ok
        weight = valid.to(sampled.dtype)
        sampled = sampled * weight
        if (sx, sy) == (1, 1):
            return sampled, valid
        frac = F.avg_pool2d(weight, (sy, sx))
        out = F.avg_pool2d(sampled, (sy, sx)) / frac.clamp(min=1e-6)
        mask = frac >= 0.5
        return out * mask.to(out.dtype), mask


def depth_to_camera(depth: Tensor, src_camera: CylindricalCamera, dst_camera: Camera) -> Tensor:
    """Cylindrical depth ``[B,1,h,w]`` of ``src_camera`` as ``dst_camera``'s depth ``[B,1,H,W]`` (the same
    centre and axes): each destination pixel's ray is looked up in the cylinder (nearest pixel, so that no
    depth is blended across an edge) and the point there expressed in the destination's depth (range for
    equirectangular, z for pinhole, horizontal distance for a cylinder). 0 where the cylinder does not see
    (e.g. above and below its band) or its depth is unknown.
    """
    b = depth.shape[0]
    rays = dst_camera.rays(dst_camera.pixel_grid(1, device=depth.device, dtype=torch.float64))
    uv = src_camera.project(rays).expand(b, -1, -1, -1)
    d, valid = sample_image(depth.double(), uv.round(), src_camera.wraps)
    valid = valid & src_camera.projectable(rays) & (d > 0)
    horizontal = torch.sqrt(rays[:, 0:1] ** 2 + rays[:, 2:3] ** 2).clamp(min=1e-12)
    points = rays / horizontal * d  # cylindrical depth d: the horizontal distance of the point
    out = dst_camera.depth_of(points)
    return torch.where(valid, out, torch.zeros(())).to(depth.dtype)
