"""View-synthesis losses, all wrap-aware at the left/right seam of a full panorama.

The paper's objective (eq. 1) over scales ``s`` and sources::

    L = sum_s ( sum_src L_pixel + lambda_s L_smooth + sum_src lambda_e L_exp )

* ``L_pixel`` (eq. 3): L1 photometric error between the target and the source warped into it, weighted by
  the explainability mask ``E`` (and by an optional static mask of pixels to use), averaged over valid pixels;
* ``L_smooth`` (eq. 4): ``|d2D/dx2| + |d2D/dxdy| + |d2D/dydx| + |d2D/dy2|`` of the disparity, weighted by
  ``1 / 2^s`` at scale ``s`` as in SfMLearner's implementation; or the image-aware smoothness used on
  Headcam (weight ``lambda_m``);
* ``L_exp``: cross-entropy of ``E`` towards "explainable" (1).

Improved variants (selectable in :class:`LossConfig`): SSIM + L1 photometric error, per-pixel minimum
reprojection over sources, auto-masking of pixels that look static, and computing the photometric term on
disparities upsampled to full resolution (the monodepth2 recipe).

Image tensors are ``[B,3,H,W]`` in ``[0, 1]``; disparities ``[B,1,H,W]`` (1 / depth); explainability masks
``[B,S,H,W]`` in ``(0, 1)``; poses ``[B,S,4,4]`` (target-to-source transforms).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from .errors import InputError, check_shape
from .geometry import Camera, column_difference, inverse_warp, pad_for_window, resize_image

__all__ = [
    "LossConfig",
    "LossOutput",
    "dense_depth_term",
    "explainability_loss",
    "gradient_x",
    "gradient_y",
    "image_aware_smoothness",
    "image_pyramid",
    "min_reprojection_term",
    "per_source_terms",
    "photometric_error",
    "second_order_smoothness",
    "second_order_terms",
    "sfm_pose_term",
    "smoothness_terms",
    "sparse_depth_term",
    "ssim_error",
    "view_synthesis_loss",
    "warp_sources",
]


# ----------------------------------------------------------------------------- finite differences
gradient_x = column_difference  # the forward difference along the width, across the seam with ``wrap``


def gradient_y(t: Tensor) -> Tensor:
    """Forward difference along the height (never wraps): ``[..., H, W] -> [..., H-1, W]``."""
    return t[..., 1:, :] - t[..., :-1, :]


def second_order_terms(disp: Tensor, wrap: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The four second derivatives of eq. 4: ``(d2/dx2, d2/dxdy, d2/dydx, d2/dy2)`` of ``disp [B,1,H,W]``.

    Column ``j`` of ``d2/dx2`` is ``D[j+2] - 2 D[j+1] + D[j]``; with ``wrap`` there are ``W`` columns (the
    last two cross the seam), without ``W - 2``, equal to the first ``W - 2`` of the wrapped ones.
    """
    dx = gradient_x(disp, wrap)
    dy = gradient_y(disp)
    return gradient_x(dx, wrap), gradient_y(dx), gradient_x(dy, wrap), gradient_y(dy)


def second_order_smoothness(disp: Tensor, wrap: bool) -> Tensor:
    """Eq. 4 averaged over pixels: mean ``|dxx| + |dxy| + |dyx| + |dyy|`` of ``disp [B,1,H,W]`` -> scalar."""
    return sum(t.abs().mean() for t in second_order_terms(disp, wrap))  # type: ignore[return-value]


def image_aware_smoothness(
    disp: Tensor, image: Tensor, wrap: bool, order: int = 1, mean_normalize: bool = False
) -> Tensor:
    """Disparity smoothness that is relaxed at image edges -> scalar.

    ``order=1``: ``|dD/dx| exp(-|dI/dx|) + |dD/dy| exp(-|dI/dy|)`` (first order, as used on Headcam).
    ``order=2``: ``exp(-|lap I|) (|d2D/dx2| + |d2D/dxdy| + |d2D/dy2|)`` with the image Laplacian, the form
    written in the paper after Wang et al. Image derivatives are averaged over colour channels.

    Args:
        disp: ``[B,1,H,W]`` disparity.
        image: ``[B,3,H,W]`` image of the same size.
        wrap: differences across the seam.
        mean_normalize: divide the disparity by its per-image mean first (scale invariance).
    """
    if mean_normalize:
        disp = disp / disp.mean(dim=(2, 3), keepdim=True).clamp(min=1e-7)
    if order == 1:
        wx = torch.exp(-gradient_x(image, wrap).abs().mean(1, keepdim=True))
        wy = torch.exp(-gradient_y(image).abs().mean(1, keepdim=True))
        return (gradient_x(disp, wrap).abs() * wx).mean() + (gradient_y(disp).abs() * wy).mean()
    if order == 2:
        dxx, dxy, _, dyy = second_order_terms(disp, wrap)
        ixx, _, _, iyy = second_order_terms(image, wrap)
        # align every term on the rows/columns they all have: rows 0..H-3, columns 0..W-3 (or all with wrap)
        h, w = dyy.shape[-2], dxx.shape[-1]
        lap = (ixx[..., :h, :w] + iyy[..., :h, :w]).abs().mean(1, keepdim=True)
        weight = torch.exp(-lap)
        d = dxx[..., :h, :w].abs() + dxy[..., :h, :w].abs() + dyy[..., :h, :w].abs()
        return (weight * d).mean()
    raise InputError(f"image-aware smoothness order must be 1 or 2, got {order}")


# ----------------------------------------------------------------------------- photometric errors
def ssim_error(x: Tensor, y: Tensor, wrap: bool) -> Tensor:
    """Structural dissimilarity ``(1 - SSIM) / 2`` over 3x3 windows, ``[B,C,H,W] -> [B,1,H,W]`` in [0, 1].

    Windows wrap around the seam when ``wrap``; the top and bottom rows use reflection.
    """
    c1, c2 = 0.01**2, 0.03**2
    xp, yp = pad_for_window(x, wrap), pad_for_window(y, wrap)
    stacked = torch.cat((xp, yp, xp * xp, yp * yp, xp * yp), 1)
    # a depthwise 3x3 box filter: several times faster than avg_pool2d on the CPU, forward and backward
    box = torch.full((stacked.shape[1], 1, 3, 3), 1.0 / 9, dtype=stacked.dtype, device=stacked.device)
    pooled = F.conv2d(stacked, box, groups=stacked.shape[1])
    mx, my, mxx, myy, mxy = pooled.chunk(5, 1)
    sx, sy, sxy = mxx - mx * mx, myy - my * my, mxy - mx * my
    ssim = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sx + sy + c2))
    return ((1 - ssim) / 2).clamp(0, 1).mean(1, keepdim=True)


def photometric_error(target: Tensor, warped: Tensor, ssim_weight: float = 0.0, wrap: bool = False) -> Tensor:
    """Per-pixel photometric error ``[B,1,H,W]``: L1 over channels, optionally mixed with SSIM.

    ``ssim_weight * ssim_error + (1 - ssim_weight) * L1``; ``ssim_weight = 0`` is the paper's L1 (eq. 3).
    """
    l1 = (target - warped).abs().mean(1, keepdim=True)
    if ssim_weight <= 0:
        return l1
    return ssim_weight * ssim_error(target, warped, wrap) + (1 - ssim_weight) * l1


def explainability_loss(mask: Tensor) -> Tensor:
    """Cross-entropy of explainability masks ``[B,S,H,W]`` (probabilities) towards 1 -> scalar."""
    return F.binary_cross_entropy(mask, torch.ones_like(mask))


# ----------------------------------------------------------------------------- pyramids
def image_pyramid(image: Tensor, sizes: list[tuple[int, int]]) -> list[Tensor]:
    """Area-downsampled copies of ``image [..., C, H, W]`` at ``sizes`` = ``[(H_s, W_s), ...]``.

    Leading dimensions are flattened for the resampling and restored; the full size returns ``image``.
    """
    lead = image.shape[:-3]
    flat = image.reshape(-1, *image.shape[-3:])
    out = []
    for h, w in sizes:
        if (h, w) == tuple(image.shape[-2:]):
            out.append(image)
        else:
            out.append(F.interpolate(flat, size=(h, w), mode="area").reshape(*lead, image.shape[-3], h, w))
    return out


# ----------------------------------------------------------------------------- the total
@dataclass
class LossConfig:
    """Weights and switches of the multi-scale view-synthesis loss (defaults: the paper on SYNTHIA).

    Attributes:
        smooth_weight: ``lambda_s`` of the second-order smoothness (eq. 4).
        image_smooth_weight: ``lambda_m`` of the image-aware smoothness (0.2 on Headcam).
        image_smooth_order: 1 (first-order, edge-aware) or 2 (Laplacian-weighted second order).
        smooth_mean_normalize: divide disparities by their mean before the image-aware smoothness.
        explain_weight: ``lambda_e`` of the explainability regulariser (0 disables masks).
        smooth_scale_decay: divide smoothness weights by ``2^s`` at scale ``s`` (SfMLearner).
        ssim_weight: weight of SSIM in the photometric error (0 = the paper's L1; 0.85 = monodepth2).
        min_reprojection: per pixel, the minimum photometric error over sources instead of the sum.
        automask: ignore pixels whose error without warping is lower than with warping (static scene
            parts, objects moving with the camera).
        full_resolution: upsample every scale's disparity to the input size for the photometric term.
        sfm_depth_weight: weight of :func:`sparse_depth_term` (the ride's adjusted points; 0: none).
        sfm_pose_weight: weight of :func:`sfm_pose_term` (the pose network taught the adjusted poses).
        sfm_dense_weight: weight of :func:`dense_depth_term` (each frame's depth fused with its
            neighbours' by the adjusted poses; 0: none).
        sfm_synthesis: warp the sources with the ride's adjusted poses where it has them, not the predicted.
    """

    smooth_weight: float = 2.0
    image_smooth_weight: float = 0.0
    image_smooth_order: int = 1
    smooth_mean_normalize: bool = False
    explain_weight: float = 0.0
    smooth_scale_decay: bool = True
    ssim_weight: float = 0.0
    min_reprojection: bool = False
    automask: bool = False
    full_resolution: bool = False
    sfm_depth_weight: float = 0.0
    sfm_pose_weight: float = 0.0
    sfm_dense_weight: float = 0.0
    sfm_synthesis: bool = False

    def __post_init__(self) -> None:
        for name in (
            "smooth_weight",
            "image_smooth_weight",
            "explain_weight",
            "sfm_depth_weight",
            "sfm_pose_weight",
            "sfm_dense_weight",
        ):
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.ssim_weight <= 1:
            raise InputError(f"ssim_weight must be in [0, 1], got {self.ssim_weight}")
        if self.image_smooth_order not in (1, 2):
            raise InputError(f"image_smooth_order must be 1 or 2, got {self.image_smooth_order}")


@dataclass
class LossOutput:
    """The total loss and every term (scalars summed over scales), plus finest-scale maps for logging.

    ``warped`` ``[B,S,3,H,W]`` and ``error`` ``[B,1,H,W]`` (the photometric error used, per pixel) are
    detached.
    """

    total: Tensor
    terms: dict[str, Tensor] = field(default_factory=dict)
    warped: Tensor | None = None
    error: Tensor | None = None


def _masked_mean(x: Tensor, weight: Tensor) -> Tensor:
    return (x * weight).sum() / weight.sum().clamp(min=1.0)


class _IdentityErrors:
    """Photometric errors of the unwarped sources, per size (auto-masking): computed once per size, since
    every scale of a full-resolution loss shares the full size."""

    def __init__(self, ssim_weight: float, wrap: bool) -> None:
        self.ssim_weight, self.wrap = ssim_weight, wrap
        self.cache: dict[tuple[int, int], list[Tensor]] = {}

    def __call__(self, tgt: Tensor, src: Tensor) -> list[Tensor]:
        """``tgt [B,3,H,W]``, ``src [B,S,3,H,W]`` -> per source ``[B,1,H,W]`` (no gradient)."""
        size = tuple(tgt.shape[-2:])
        if size not in self.cache:
            with torch.no_grad():
                self.cache[size] = [  # type: ignore[index]
                    photometric_error(tgt, src[:, k], self.ssim_weight, self.wrap)
                    for k in range(src.shape[1])
                ]
        return self.cache[size]  # type: ignore[index]


def min_reprojection_term(
    errors: list[Tensor], valids: list[Tensor], weight: Tensor, identity: list[Tensor] | None
) -> tuple[Tensor, Tensor]:
    """Per pixel the smallest error over the sources (monodepth2), averaged -> ``(scalar, map [B,1,H,W])``.

    Args:
        errors: per source ``[B,1,H,W]`` photometric errors of the warped source.
        valids: per source ``[B,1,H,W]`` 0/1: the source sees the pixel. A source that cannot see a pixel
            never wins the minimum; a pixel no source sees is not used.
        weight: ``[B,1,H,W]`` pixel weights (static mask).
        identity: with auto-masking, per source the error of the *unwarped* source; pixels whose best
            warped error is not below the best unwarped one are ignored. ``None``: no auto-masking.
    """
    err = torch.cat(errors, 1)  # [B,S,H,W]
    val = torch.cat(valids, 1)
    big = err.detach().max() + 1
    err = torch.where(val > 0, err, big)
    best, _ = err.min(1, keepdim=True)
    use = weight * (val.amax(1, keepdim=True))
    if identity is not None:
        ident = torch.cat(identity, 1)
        ident = ident + 1e-5 * torch.randn_like(ident)  # break ties as monodepth2 does
        use = use * (best < ident.min(1, keepdim=True).values).to(use.dtype)
    return _masked_mean(best, use), best.detach()


def per_source_terms(
    errors: list[Tensor],
    valids: list[Tensor],
    weight: Tensor,
    identity: list[Tensor] | None,
    explainability: Tensor | None,
) -> tuple[list[Tensor], Tensor]:
    """The paper's photometric term (eq. 3): one masked mean per source -> ``(terms, mean map [B,1,H,W])``.

    Args:
        errors, valids, weight: as in :func:`min_reprojection_term`.
        identity: with auto-masking, per source the error of the unwarped source: pixels where warping
            does not beat it are ignored. ``None``: no auto-masking.
        explainability: ``[B,S,H,W]`` masks at this size multiplying each source's error, or ``None``.
    """
    n_src = len(errors)
    terms, err_map = [], torch.zeros_like(errors[0])
    for k in range(n_src):
        use = weight * valids[k]
        if identity is not None:
            use = use * (errors[k] < identity[k]).to(use.dtype).detach()
        e = errors[k]
        if explainability is not None:
            e = e * explainability[:, k : k + 1]
        terms.append(_masked_mean(e, use))
        err_map = err_map + e.detach() / n_src
    return terms, err_map


def smoothness_terms(disp: Tensor, image: Tensor, scale: int, cfg: LossConfig, wrap: bool) -> list[Tensor]:
    """The smoothness terms of one scale: second-order (eq. 4) and image-aware, as configured.

    ``disp [B,1,H_s,W_s]``, ``image [B,3,H_s,W_s]`` (the target at that scale); each weight is divided
    by ``2^scale`` with ``cfg.smooth_scale_decay``.
    """
    decay = 2.0**scale if cfg.smooth_scale_decay else 1.0
    terms = []
    if cfg.smooth_weight > 0:
        terms.append(cfg.smooth_weight / decay * second_order_smoothness(disp, wrap))
    if cfg.image_smooth_weight > 0:
        terms.append(
            cfg.image_smooth_weight
            / decay
            * image_aware_smoothness(disp, image, wrap, cfg.image_smooth_order, cfg.smooth_mean_normalize)
        )
    return terms


def warp_sources(
    sources: Tensor, depth: Tensor, poses: Tensor, camera: Camera, wrap: bool
) -> tuple[list[Tensor], list[Tensor]]:
    """Every source ``[B,S,3,H,W]`` warped into the target with ``depth [B,1,H,W]`` and ``poses [B,S,4,4]``.

    Returns per source ``(warped [B,3,H,W], valid [B,1,H,W] as depth's dtype)``.
    """
    warps, valids = [], []
    for k in range(sources.shape[1]):
        warped, valid = inverse_warp(sources[:, k], depth, poses[:, k], camera, wrap=wrap)
        warps.append(warped)
        valids.append(valid.to(depth.dtype))
    return warps, valids


def _photometric_terms(
    cfg: LossConfig,
    target: Tensor,
    sources: Tensor,
    disp: Tensor,
    poses: Tensor,
    camera: Camera,
    masks: Tensor | None,
    static_mask: Tensor | None,
    identity: _IdentityErrors | None,
    wrap: bool,
) -> tuple[list[Tensor], list[Tensor], Tensor]:
    """The photometric term(s) of one scale: every source warped with ``disp`` (resized to the images'
    size with ``full_resolution``) into ``target [B,3,h,w]``, compared, and reduced per source (the paper)
    or by the per-pixel minimum. Returns ``(terms, warped sources, error map [B,1,h,w])``."""
    h, w = target.shape[-2:]
    cam = camera.resized(w, h) if (w, h) != camera.size else camera
    disp = resize_image(disp, (h, w), wrap) if cfg.full_resolution else disp
    depth = 1.0 / disp.clamp(min=1e-6)
    weight = torch.ones_like(depth)
    if static_mask is not None:
        weight = weight * image_pyramid(static_mask.to(depth.dtype), [(h, w)])[0]
    warps, valids = warp_sources(sources, depth, poses, cam, wrap)
    errors = [photometric_error(target, warped, cfg.ssim_weight, wrap) for warped in warps]
    ident = identity(target, sources) if identity is not None else None
    if cfg.min_reprojection:
        term, err_map = min_reprojection_term(errors, valids, weight, ident)
        return [term], warps, err_map
    masks = None if masks is None else resize_image(masks, (h, w), wrap)
    terms, err_map = per_source_terms(errors, valids, weight, ident, masks)
    return terms, warps, err_map


def view_synthesis_loss(
    target: Tensor,
    sources: Tensor,
    disparities: list[Tensor],
    poses: Tensor,
    camera: Camera,
    config: LossConfig | None = None,
    explainability: list[Tensor] | None = None,
    static_mask: Tensor | None = None,
    wrap: bool | None = None,
) -> LossOutput:
    """The multi-scale objective of eq. 1 (and its improved variants, per ``config``).

    Per scale: warp every source with the disparity, take the photometric term (the paper's per-source
    sum, :func:`per_source_terms`, or the per-pixel minimum, :func:`min_reprojection_term`), the
    explainability regulariser and the smoothness (:func:`smoothness_terms`); sum over scales.

    Args:
        target: ``[B,3,H,W]`` target images in [0, 1].
        sources: ``[B,S,3,H,W]`` source images.
        disparities: per scale, finest first, ``[B,1,H_s,W_s]`` target disparities (1 / depth).
        poses: ``[B,S,4,4]`` transforms from the target camera to each source camera, in the depth's unit.
        camera: camera of the full-resolution images (``W x H``); smaller scales use ``camera.resized``.
        config: weights and variants (default: the paper's SYNTHIA setting).
        explainability: per scale ``[B,S,H_s,W_s]`` masks in (0, 1), or ``None`` (all ones).
        static_mask: ``[B,1,H,W]`` or ``[1,1,H,W]`` weights in [0, 1] of pixels to use (e.g. 0 on a helmet).
        wrap: wrap at the seam; ``None``: if the camera wraps.

    Returns:
        :class:`LossOutput` with terms ``photometric``, ``smooth``, ``explain`` and ``total``.
    """
    cfg = config or LossConfig()
    wrap = camera.wraps if wrap is None else wrap
    b, n_src = sources.shape[:2]
    check_shape(poses, f"{b},{n_src},4,4", "poses")
    if cfg.min_reprojection and explainability is not None and cfg.explain_weight > 0:
        raise InputError("explainability masks and minimum reprojection are alternatives: use one")
    sizes = [tuple(d.shape[-2:]) for d in disparities]
    target_pyramid = image_pyramid(target, sizes)  # the smoothness's images, at the disparities' sizes
    # the photometric term's images: the disparities' sizes, or all the full size with full_resolution
    if cfg.full_resolution:
        photo_targets, photo_sources = [target] * len(sizes), [sources] * len(sizes)
    else:
        photo_targets, photo_sources = target_pyramid, image_pyramid(sources, sizes)
    identity = _IdentityErrors(cfg.ssim_weight, wrap) if cfg.automask else None
    zero = target.new_zeros(())
    photometric, smooth, explain = zero, zero, zero
    warped_log, error_log = None, None
    for s, disp in enumerate(disparities):
        masks = explainability[s] if explainability is not None else None
        terms, warps, err_map = _photometric_terms(
            cfg, photo_targets[s], photo_sources[s], disp, poses, camera, masks, static_mask, identity, wrap
        )
        for term in terms:
            photometric = photometric + term
        if explainability is not None and cfg.explain_weight > 0:
            explain = explain + cfg.explain_weight * n_src * explainability_loss(explainability[s])
        for term in smoothness_terms(disp, target_pyramid[s], s, cfg, wrap):
            smooth = smooth + term
        if s == 0:
            warped_log, error_log = torch.stack(warps, 1).detach(), err_map
    total = photometric + smooth + explain
    terms = {"photometric": photometric, "smooth": smooth, "explain": explain, "total": total}
    return LossOutput(total=total, terms=terms, warped=warped_log, error=error_log)


# ----------------------------------------------------------------------------- the ride's own geometry
def sparse_depth_term(disparity: Tensor, sparse: Tensor, floor: float = 1e-3) -> Tensor:
    """How far the depth is from the ride's adjusted points: per point, Cauchy's ``log(1 + (r / sigma)^2)``
    of ``r = log(depth / point's depth)``, so that a point far off (a wrong match, a moving object) pulls
    little; averaged over the points (0 without any).

    Args:
        disparity: ``[B,1,H,W]`` the finest disparity (1 / depth).
        sparse: ``[B,2,H,W]``: the points' depth (0: no point) and relative standard deviation ``sigma``
            (:meth:`cylsfm.data.geometry.RideGeometry.depth_map`).
        floor: the smallest ``sigma`` used.
    """
    check_shape(sparse, f"{disparity.shape[0]},2,{disparity.shape[2]},{disparity.shape[3]}", "targets")
    has = sparse[:, :1] > 0
    if not bool(has.any()):
        return disparity.new_zeros(())
    log_depth = -torch.log(disparity.clamp(min=1e-6))
    r = (log_depth - torch.log(sparse[:, :1].clamp(min=1e-6)))[has]
    sigma = sparse[:, 1:][has].clamp(min=floor)
    return torch.log1p((r / sigma) ** 2).mean()


#: The smallest spread a fused depth is trusted to (:func:`dense_depth_term`).
DENSE_FLOOR = 0.05


def dense_depth_term(disparity: Tensor, dense: Tensor) -> Tensor:
    """:func:`sparse_depth_term` against the ride's fused depth ``dense`` ``[B,2,H,W]`` (each frame's depth
    fused with its neighbours' by the adjusted poses, 0 where none, and the frames' spread in log depth as
    ``sigma``, never below :data:`DENSE_FLOOR`: :meth:`cylsfm.data.geometry.RideGeometry.fused_map`),
    averaged over the pixels that have one; ``disparity`` ``[B,1,H,W]``."""
    return sparse_depth_term(disparity, dense, DENSE_FLOOR)


def sfm_pose_term(poses: Tensor, sfm_poses: Tensor, step: Tensor) -> Tensor:
    """How far the predicted poses are from the ride's adjusted ones: the translation's error in the ride's
    median steps, plus the rotation's (``|R - R_sfm|_F / sqrt(2)``, about the angle in radians), averaged
    over the pairs that have the ride's geometry (0 without any).

    Args:
        poses: ``[B,S,4,4]`` predicted ``T_tgt_to_src``; ``sfm_poses``: the adjusted ones, in the depth's
            unit; ``step``: ``[B,S]`` the ride's median step length (0: no geometry for the pair).
    """
    check_shape(sfm_poses, ",".join(str(n) for n in poses.shape), "sfm_poses")
    weight = (step > 0).to(poses.dtype)
    if not bool((weight > 0).any()):
        return poses.new_zeros(())
    t = (poses[..., :3, 3] - sfm_poses[..., :3, 3]).norm(dim=-1) / step.clamp(min=1e-6)
    rot = (poses[..., :3, :3] - sfm_poses[..., :3, :3]).flatten(-2).norm(dim=-1) / 2**0.5
    return ((t + rot) * weight).sum() / weight.sum()
