"""The photometric error of a rigid motion between two frames, as direct alignment measures it.

A target image ``I_t`` with depth ``D_t`` and a source image ``I_s`` are compared pixel by pixel at a
relative pose ``T`` (``p_s = T p_t``): ``r(p) = I_s(project(T unproject(D_t)(p))) - I_t(p)``, on grey images
normalised to zero mean and unit variance (a change of exposure between frames costs nothing), over an
image pyramid (each level halves the size, area averaging; the depth is averaged as disparity). On full
panoramas every sample and every image gradient wraps across the seam. This module makes the levels,
the residuals, their Jacobian with respect to a left increment of the pose and the robust (Huber) cost;
:mod:`cylsfm.geometry.align` descends on them. :func:`photometric_costs` and :func:`photometric_inliers`
measure given poses.

A mask fixed to the camera (a helmet, a mount, the car's roof: the same pixels in every frame) takes those
pixels out: a target pixel under the mask is not compared, and neither is one whose point lands on the
mask in the source (it is hidden there: it counts neither as compared nor as lost).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError, ShapeError, check_shape
from .cameras import Camera
from .jacobian import projection_jacobian
from .seam import circular_pad
from .warp import sample_image, transform_points

__all__ = ["half_size", "photometric_costs", "photometric_inliers", "resize_depth"]

#: Grey from RGB (ITU-R BT.601 luma weights).
_LUMA = (0.299, 0.587, 0.114)
#: The smallest image height a pyramid level may have.
MIN_HEIGHT = 8


@dataclass
class Level:
    """One level of the pyramid: the target, the source and the target's points at that size."""

    camera: Camera
    target: Tensor  # [B,1,h,w] grey, normalised
    source: Tensor  # [B,3,h,w] grey source and its two derivatives (d/du, d/dv); [B,4,h,w]: and where
    # the source is not free of the mask (1), dilated by a pixel so that no derivative reads the occluder
    points: Tensor  # [B,3,h,w] target points (from the depth)
    has_depth: Tensor  # [B,1,h,w] bool
    wrap: bool


@dataclass
class Residuals:
    """The residuals at one pose."""

    r: Tensor  # [B,1,h,w]
    valid: Tensor  # [B,1,h,w] bool
    usable: Tensor  # [B] the target pixels with a depth that the source does not hide under its mask


def _grey(images: Tensor, mask: Tensor | None = None) -> Tensor:
    """Grey ``[B,1,H,W]``, normalised to zero mean and unit variance (over the pixels of ``mask``)."""
    w = torch.tensor(_LUMA, dtype=images.dtype, device=images.device).reshape(1, 3, 1, 1)
    g = (images * w).sum(1, keepdim=True)
    if mask is None:
        mean = g.mean((2, 3), keepdim=True)
        std = g.std((2, 3), keepdim=True).clamp(min=1e-6)
        return (g - mean) / std
    n = mask.sum((2, 3), keepdim=True).clamp(min=2)
    mean = (g * mask).sum((2, 3), keepdim=True) / n
    var = (((g - mean) ** 2) * mask).sum((2, 3), keepdim=True) / (n - 1)
    return (g - mean) / var.sqrt().clamp(min=1e-6)


def _dilate(dirty: Tensor, wrap: bool) -> Tensor:
    """``[B,1,h,w]`` float 0/1 -> 1 where any pixel of the 3x3 neighbourhood is 1 (across the seam when
    ``wrap``; beyond the image's edges as at them)."""
    x = circular_pad(dirty, 1, 1) if wrap else F.pad(dirty, (1, 1, 0, 0), mode="replicate")
    x = F.pad(x, (0, 0, 1, 1), mode="replicate")
    return F.max_pool2d(x, 3, stride=1)


def _gradients(g: Tensor, wrap: bool) -> Tensor:
    """``[B,1,h,w]`` -> ``[B,3,h,w]``: the image, its central differences along u (wrapping) and v."""
    padded = circular_pad(g, 1, 1) if wrap else F.pad(g, (1, 1, 0, 0), mode="replicate")
    du = 0.5 * (padded[..., 2:] - padded[..., :-2])
    rows = F.pad(g, (0, 0, 1, 1), mode="replicate")
    dv = 0.5 * (rows[..., 2:, :] - rows[..., :-2, :])
    return torch.cat((g, du, dv), 1)


def _half(x: Tensor) -> Tensor:
    h, w = x.shape[-2:]
    if h % 2 == 0 and w % 2 == 0:
        return F.avg_pool2d(x, 2)
    return F.interpolate(x, size=(h // 2, w // 2), mode="area")


def half_size(
    target: Tensor, source: Tensor, depth: Tensor, camera: Camera, mask: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor, Camera, Tensor | None] | None:
    """Images ``[B,3,H,W]``, the targets' depth ``[B,1,H,W]``, their camera and a mask ``[N,1,H,W]`` (or
    ``None``) at half the width and height, as :func:`align`'s own pyramid makes its next level (images
    and mask averaged over 2x2 pixels, depth by :func:`resize_depth`); ``None`` where the half would be
    smaller than a pyramid level may be."""
    h, w = target.shape[-2:]
    if h // 2 < MIN_HEIGHT or w // 2 < MIN_HEIGHT:
        return None
    small = camera.resized(w // 2, h // 2)
    half_mask = None if mask is None else _half(mask.float())
    return _half(target), _half(source), resize_depth(depth, (h // 2, w // 2)), small, half_mask


def resize_depth(depth: Tensor, size: tuple[int, int]) -> Tensor:
    """Depth ``[B,1,H,W]`` (``<= 0``: unknown) -> ``[B,1,h,w]`` at ``size = (h, w)``: the area average of
    the disparity over the pixels with a depth, where they cover more than half the area; 0 elsewhere."""
    has = depth > 0
    disp = torch.where(has, 1.0 / depth.clamp(min=1e-12), torch.zeros_like(depth)).float()
    weight = has.float()
    if tuple(depth.shape[-2:]) != tuple(size):
        disp = F.interpolate(disp, size=size, mode="area")
        weight = F.interpolate(weight, size=size, mode="area")
    out = torch.where(weight > 0.5, weight / disp.clamp(min=1e-12), torch.zeros_like(disp))
    return torch.where(torch.isfinite(out), out, torch.zeros_like(out))


def pyramid(
    target: Tensor,
    source: Tensor,
    depth: Tensor,
    camera: Camera,
    wrap: bool,
    levels: int,
    mask: Tensor | None = None,
) -> list[Level]:
    """The levels, finest first (``mask`` ``[B,1,H,W]`` float: 1 where the scene is seen, or ``None``)."""
    tgt, src = _grey(target.float(), mask), _grey(source.float(), mask)
    out = []
    for level in range(levels):
        if level:
            if tgt.shape[-2] // 2 < MIN_HEIGHT or tgt.shape[-1] // 2 < MIN_HEIGHT:
                break
            tgt, src = _half(tgt), _half(src)
            mask = _half(mask) if mask is not None else None
        h, w = tgt.shape[-2:]
        cam = camera if level == 0 else camera.resized(w, h)
        d = resize_depth(depth, (h, w))
        ok = d > 0
        d = torch.where(ok, d, torch.ones_like(d))
        grads = _gradients(src, wrap)
        if mask is not None:  # a pixel the occluder touches at this level is not used
            clean = mask > 0.999
            ok = ok & clean
            grads = torch.cat((grads, _dilate((~clean).float(), wrap)), 1)
        out.append(Level(cam, tgt, grads, cam.unproject(d), ok, wrap))
    return out


def residuals(lv: Level, pose: Tensor) -> tuple[Residuals, Tensor, Tensor]:
    """The residuals at ``pose`` ``[B,4,4]``, with the moved points ``[B,3,h,w]`` and the sampled source
    ``[B,C,h,w]`` that their Jacobian (:func:`jacobian`) is made of."""
    points = transform_points(pose, lv.points)
    uv = lv.camera.project(points)
    sampled, valid = sample_image(lv.source, uv, lv.wrap)
    valid = valid & lv.camera.projectable(points) & lv.has_depth
    usable = lv.has_depth.flatten(1).sum(1)
    if sampled.shape[1] == 4:  # the source's mask: what lands on it is hidden, neither compared nor lost
        hidden = valid & (sampled[:, 3:] > 0)  # any weight on a pixel near the occluder
        valid = valid & ~hidden
        usable = usable - hidden.flatten(1).sum(1)
    r = sampled[:, :1] - lv.target
    return Residuals(r, valid, usable), points, sampled


def jacobian(camera: Camera, points: Tensor, sampled: Tensor) -> Tensor:
    """The derivative of the residuals with respect to a left increment ``d = (v, w)`` of the pose
    (translation, axis-angle), ``dI/dd = grad I_s . dproject/dP . [I | -[P]x]``: ``[B,6,h,w]`` from the moved
    points ``[B,3,h,w]`` and the source sampled there with its derivatives along u and v ``[B,>=3,h,w]``
    (:func:`residuals`)."""
    jp = projection_jacobian(camera, points)  # [B,2,3,h,w]
    g = sampled[:, 1:2] * jp[:, 0] + sampled[:, 2:3] * jp[:, 1]  # dI/dP [B,3,h,w]
    px, py, pz = points.unbind(1)
    gx, gy, gz = g.unbind(1)
    rot = torch.stack((py * gz - pz * gy, pz * gx - px * gz, px * gy - py * gx), 1)  # points x g
    return torch.cat((g, rot), 1)


def robust_scale(lin: Residuals) -> Tensor:
    """Robust standard deviation of the residuals ``[B]`` (1.4826 x median |r| over valid pixels)."""
    a = torch.where(lin.valid, lin.r.abs(), torch.full_like(lin.r, float("nan"))).flatten(1)
    med = torch.nanmedian(a, dim=1).values
    return torch.nan_to_num(1.4826 * med, nan=1.0).clamp(min=1e-3)


def robust_cost(lin: Residuals, k: Tensor) -> Tensor:
    """Mean Huber cost ``[B]`` over the target pixels with a depth (``k [B]``: the thresholds). A pixel whose
    point leaves the source's view costs as much as a residual of two thresholds: were it free, a pose
    that pushes the worst-fitting pixels out of the view would look better than the true one."""
    a = lin.r.abs()
    kk = k.reshape(-1, 1, 1, 1)
    rho = torch.where(a <= kk, 0.5 * a * a, kk * (a - 0.5 * kk))
    n_valid = lin.valid.flatten(1).sum(1)
    lost = (lin.usable - n_valid).clamp(min=0) * 1.5 * k * k
    cost = ((rho * lin.valid).flatten(1).sum(1) + lost) / lin.usable.clamp(min=1)
    return torch.where(n_valid > 0, cost, torch.full_like(cost, float("inf")))


def checked_mask(mask: Tensor | None, target: Tensor) -> Tensor | None:
    """The mask checked and as float ``[B,1,H,W]`` on the target's device."""
    if mask is None:
        return None
    check_shape(mask, "N,1,H,W", "mask")
    if mask.shape[-2:] != target.shape[-2:] or mask.shape[0] not in (1, target.shape[0]):
        raise ShapeError(f"mask {tuple(mask.shape)} does not fit images {tuple(target.shape)}")
    return mask.to(device=target.device, dtype=torch.float32).expand(target.shape[0], -1, -1, -1)


def photometric_costs(
    target: Tensor,
    source: Tensor,
    depth: Tensor,
    poses: Tensor,
    camera: Camera,
    wrap: bool | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """The robust photometric cost ``[B,K]`` of ``K`` poses per pair, comparable across the ``K``.

    The cost of :func:`align` at full resolution, all ``K`` poses of a pair measured with one robust
    threshold: the smallest of theirs (the best-fitting pose's residual scale).

    Args:
        target, source: images ``[B,3,H,W]``; depth: the targets' depth ``[B,1,H,W]``.
        poses: ``T_{t->s}`` ``[B,K,4,4]``; camera, wrap, mask: as for :func:`align`.
    """
    check_shape(poses, f"{target.shape[0]},K,4,4", "poses")
    wrap = camera.wraps if wrap is None else wrap
    lv = pyramid(target, source, depth, camera, wrap, 1, checked_mask(mask, target))[0]
    lins = [residuals(lv, poses[:, i].double())[0] for i in range(poses.shape[1])]
    k = torch.stack([robust_scale(lin) for lin in lins]).min(0).values
    return torch.stack([robust_cost(lin, k) for lin in lins], 1)


def _value_range(grey: Tensor, spread: Tensor, wrap: bool) -> Tensor:
    """``[B,1,h,w]`` -> ``[B,2,h,w]``: the lowest and highest value the image takes on the way from each
    pixel towards its 8 neighbours, ``spread`` ``[B]`` (each ``<= 1``) of the way (linearly interpolated)."""
    x = circular_pad(grey, 1, 1) if wrap else F.pad(grey, (1, 1, 0, 0), mode="replicate")
    x = F.pad(x, (0, 0, 1, 1), mode="replicate")
    h, w = grey.shape[-2:]
    around = torch.stack([x[..., a : a + h, b : b + w] for a in range(3) for b in range(3)], 0)  # [9,B,1,h,w]
    values = grey + spread.to(grey).reshape(-1, 1, 1, 1) * (around - grey)
    return torch.cat((values.amin(0), values.amax(0)), 1)


def photometric_inliers(
    target: Tensor,
    source: Tensor,
    depth: Tensor,
    poses: Tensor,
    camera: Camera,
    threshold: float = 0.25,
    min_gradient: float = 0.5,
    spread: float | Tensor = 1.0,
    wrap: bool | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """The fraction ``[B]`` of the target's textured pixels with a depth whose residual at ``poses`` is
    within ``threshold`` (in standard deviations of the grey images, normalised as in :func:`align`): a
    pixel whose point leaves the source's view, or lands on the mask there, counts as an outlier.
    Textured: the target's grey gradient (the larger of the two central differences) is at least
    ``min_gradient`` standard deviations; flat pixels (sky, asphalt, plaster) fit almost any pose and
    would make two different places look alike. An absolute measure of fit, unlike :func:`align`'s cost
    (scaled by its own residuals): how much of the target's texture a rigid motion with this depth explains.

    The residual is insensitive to sampling (after Birchfield and Tomasi): a target pixel's distance to the
    range of the source's values within ``spread`` pixels of where its point lands (``1``: the 3x3
    neighbourhood; ``0``: the value there). Seen from afar, or from a few metres to the side, a texture is
    sampled at other places and scales, and even the right rigid motion leaves residuals of a pixel's
    contrast; a wrong one leaves most of them outside the neighbourhood's range.

    Args:
        target, source: images ``[B,3,H,W]``; depth: the targets' depth ``[B,1,H,W]``.
        poses: ``T_{t->s}`` ``[B,4,4]``; camera, wrap, mask: as for :func:`align`.
        spread: pixels, in ``[0, 1]``: one for every pair, or ``[B]``, one each.
    """
    check_shape(poses, f"{target.shape[0]},4,4", "poses")
    spread = torch.as_tensor(spread, dtype=torch.float32).flatten()
    if spread.numel() not in (1, target.shape[0]):
        raise ShapeError(
            f"photometric_inliers: spread must be one number or [{target.shape[0]}], got {spread.numel()}"
        )
    spread = spread.expand(target.shape[0])
    if not bool(((spread >= 0) & (spread <= 1)).all()):
        raise InputError(f"photometric_inliers: spread must be in [0, 1], got {spread.tolist()}")
    wrap = camera.wraps if wrap is None else wrap
    lv = pyramid(target, source, depth, camera, wrap, 1, checked_mask(mask, target))[0]
    lin, points, _ = residuals(lv, poses.double())
    residual = lin.r.abs()
    if bool(spread.any()):  # (a spread of 0 leaves the residual as it is)
        low_high, _ = sample_image(
            _value_range(lv.source[:, :1], spread, wrap), lv.camera.project(points), wrap
        )
        residual = torch.maximum(low_high[:, :1] - lv.target, lv.target - low_high[:, 1:]).clamp(min=0)
    grads = _gradients(lv.target, wrap)[:, 1:3].abs().amax(1, keepdim=True)  # [B,1,H,W]
    textured = lv.has_depth & (grads >= min_gradient)
    good = (lin.valid & textured & (residual <= threshold)).flatten(1).sum(1)
    return good.double() / textured.flatten(1).sum(1).clamp(min=1).double()
