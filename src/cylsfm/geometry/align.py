"""Direct photometric alignment: the relative pose that makes a source frame, warped with the target's depth,
look like the target.

For a target image ``I_t`` with depth ``D_t`` and a source image ``I_s``, :func:`align` finds the relative
pose ``T`` (``p_s = T p_t``) that minimises the robust photometric error

    ``sum_p rho(I_s(project(T unproject(D_t)(p))) - I_t(p))``

over the target's pixels ``p``, with Levenberg-Marquardt on the left increment ``T <- exp(d) T``
(``d = (v, w)``: translation, axis-angle) and the closed-form Jacobian
``dI/dd = grad I_s . dproject/dP . [I | -[P]x]``. It works on grey images normalised to zero mean and unit
variance (a change of exposure between frames costs nothing), coarse to fine over an image pyramid (each
level halves the size, area averaging; the depth is averaged as disparity), with the Huber loss at a
threshold of :attr:`AlignConfig.huber` robust standard deviations (1.4826 x the median absolute residual)
so that moving cars, occlusions and the sky count little. On full panoramas every sample and every image
gradient wraps across the seam. Everything is batched: ``B`` pairs are aligned at once. The levels, the
residuals, their Jacobian and the robust cost are :mod:`cylsfm.geometry.photometric`'s.

Several starting poses may be given per pair (the network's pose, the visual compass's yaw ...): at the
start of every level the candidates and the current estimate are compared and the cheapest one goes on,
so a bad start is dropped as soon as a level sees it.

A mask fixed to the camera (a helmet, a mount, the car's roof: the same pixels in every frame) takes those
pixels out: a target pixel under the mask is not compared, and neither is one whose point lands on the
mask in the source (it is hidden there: it counts neither as compared nor as lost). Without the mask, such
an occluder, identical in both frames, pulls every estimate towards standing still.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import InputError, ShapeError, check_shape
from .cameras import Camera
from .photometric import (
    Level,
    Residuals,
    checked_mask,
    jacobian,
    pyramid,
    residuals,
    robust_cost,
    robust_scale,
)
from .pose import axis_angle_to_matrix

__all__ = ["AlignConfig", "AlignResult", "align"]


@dataclass(frozen=True)
class AlignConfig:
    """Settings of :func:`align`.

    Attributes:
        levels: pyramid levels (each halves the width and height), fewer when the image is small.
        iterations: Levenberg-Marquardt iterations per level.
        huber: the Huber threshold in robust standard deviations of the residuals.
        damping: the initial Levenberg-Marquardt damping (relative to the diagonal).
    """

    levels: int = 3
    iterations: int = 8
    huber: float = 1.345
    damping: float = 1e-3

    def __post_init__(self) -> None:
        if self.levels < 1 or self.iterations < 0:
            raise InputError(f"levels must be >= 1 and iterations >= 0, got {self.levels}, {self.iterations}")
        if not (self.huber > 0 and self.damping > 0):
            raise InputError(f"huber and damping must be positive, got {self.huber}, {self.damping}")


@dataclass
class AlignResult:
    """What :func:`align` found for ``B`` pairs.

    Attributes:
        poses: refined relative poses ``T_{t->s}`` ``[B,4,4]`` (float64, translation in the depth's unit).
        cost: the final mean robust cost per pair ``[B]`` at the finest level.
        start_cost: the same cost of the first candidate (e.g. the network's pose) ``[B]``, measured with
            the same robust scale: ``cost <= start_cost`` always.
        start: the candidate the estimate descends from ``[B]`` (long; an index into ``init``'s ``K``).
        valid: the fraction of target pixels that were compared ``[B]``.
    """

    poses: Tensor
    cost: Tensor
    start_cost: Tensor
    start: Tensor
    valid: Tensor


def _exp(step: Tensor) -> Tensor:
    """Increments ``[B,6]`` (translation, axis-angle) -> transforms ``[B,4,4]`` (float64)."""
    out = torch.eye(4, dtype=torch.float64, device=step.device).repeat(step.shape[0], 1, 1)
    out[:, :3, :3] = axis_angle_to_matrix(step[:, 3:])
    out[:, :3, 3] = step[:, :3]
    return out


def _normal_equations(res: Residuals, jac: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """The Gauss-Newton system of the Huber cost at a linearisation (``jac`` ``[B,6,h,w]``, ``k`` ``[B]``: the
    thresholds): ``J^T W J`` ``[B,6,6]`` and ``J^T W r`` ``[B,6]`` (float64), ``W`` the Huber weights."""
    a = res.r.abs()
    kk = k.reshape(-1, 1, 1, 1)
    w = torch.where(a <= kk, torch.ones_like(a), kk / a.clamp(min=1e-12))
    w = (w * res.valid).flatten(1)
    jac = jac.flatten(2)  # [B,6,N]
    hess = torch.einsum("bin,bjn->bij", jac * w[:, None], jac).double()
    grad = torch.einsum("bin,bn->bi", jac, w * res.r.flatten(1)).double()
    return hess, grad


def _solve(hess: Tensor, grad: Tensor, damping: Tensor) -> Tensor:
    """The damped Gauss-Newton step ``[B,6]`` (float64) of a system ``[B,6,6]``, ``[B,6]``."""
    diag = torch.diagonal(hess, dim1=1, dim2=2)
    floor = 1e-9 * diag.mean(1, keepdim=True).clamp(min=1e-12)
    return -torch.linalg.solve(hess + torch.diag_embed(damping[:, None] * diag + floor), grad)


def _pick(lv: Level, poses: list[Tensor]) -> tuple[Tensor, Tensor, Tensor, Residuals, Tensor, Tensor]:
    """The cheapest of several poses per pair, all costed with the first one's robust scale: ``(pose,
    index, cost, its residuals, its Jacobian, threshold k)``. Only the residuals of every pose are computed;
    the Jacobian only at the pose picked (the same numbers as linearising every pose, for less work)."""
    res = [residuals(lv, p)[0] for p in poses]
    k = robust_scale(res[0])
    costs = torch.stack([robust_cost(r, k) for r in res])  # [K,B]
    best = costs.argmin(0)
    b = torch.arange(best.shape[0], device=best.device)
    pose = torch.stack(poses)[best, b]
    picked, points, sampled = residuals(lv, pose)
    return pose, best, costs[best, b], picked, jacobian(lv.camera, points, sampled), k


def _lm(
    lv: Level, pose: Tensor, res: Residuals, jac: Tensor, cost: Tensor, k: Tensor, config: AlignConfig
) -> tuple[Tensor, Tensor, Residuals]:
    """Levenberg-Marquardt iterations on one level from ``pose`` (its residuals, Jacobian and cost);
    returns ``(pose, cost, residuals)``. The system is formed once per accepted pose (a rejected step only
    raises the damping), and a candidate's Jacobian is made only when some pair of the batch accepts it."""
    damping = torch.full_like(cost, config.damping, dtype=torch.float64)
    hess, grad = _normal_equations(res, jac, k)
    for _ in range(config.iterations):
        cand = _exp(_solve(hess, grad, damping)) @ pose
        cand_res, points, sampled = residuals(lv, cand)
        cand_cost = robust_cost(cand_res, k)
        better = cand_cost < cost
        damping = torch.where(better, damping / 3, damping * 4).clamp(1e-7, 1e7)
        if not bool(better.any()):
            continue
        cand_hess, cand_grad = _normal_equations(cand_res, jacobian(lv.camera, points, sampled), k)
        per_matrix, per_map = better.reshape(-1, 1, 1), better.reshape(-1, 1, 1, 1)
        hess = torch.where(per_matrix, cand_hess, hess)
        grad = torch.where(better.reshape(-1, 1), cand_grad, grad)
        res = Residuals(
            torch.where(per_map, cand_res.r, res.r),
            torch.where(per_map, cand_res.valid, res.valid),
            torch.where(better, cand_res.usable, res.usable),
        )
        pose = torch.where(per_matrix, cand, pose)
        cost = torch.where(better, cand_cost, cost)
    return pose, cost, res


def align(
    target: Tensor,
    source: Tensor,
    depth: Tensor,
    init: Tensor,
    camera: Camera,
    wrap: bool | None = None,
    config: AlignConfig | None = None,
    mask: Tensor | None = None,
) -> AlignResult:
    """Refine relative poses by direct photometric alignment (see the module docstring).

    Args:
        target: target images ``[B,3,H,W]`` in [0, 1].
        source: source images ``[B,3,H,W]``.
        depth: the targets' depth ``[B,1,H,W]`` (the camera model's depth, any unit; ``<= 0``: unknown).
        init: starting poses ``T_{t->s}`` ``[B,4,4]``, or ``[B,K,4,4]`` for ``K`` candidates each (the
            first is the reference of :attr:`AlignResult.start_cost`).
        camera: the camera of all images.
        wrap: sample across the seam; ``None``: when the camera wraps (a full panorama).
        config: :class:`AlignConfig` (default settings when ``None``).
        mask: ``[B,1,H,W]`` or ``[1,1,H,W]``, 1 (or True) where the scene is seen and 0 on an occluder fixed
            to the camera (the same pixels in target and source); ``None``: every pixel.

    Returns:
        :class:`AlignResult` (``valid``: the fraction of all the target's pixels compared).
    """
    config = config or AlignConfig()
    check_shape(target, "B,3,H,W", "target")
    check_shape(source, "B,3,H,W", "source")
    check_shape(depth, "B,1,H,W", "depth")
    if (
        source.shape != target.shape
        or depth.shape[-2:] != target.shape[-2:]
        or depth.shape[0] != target.shape[0]
    ):
        raise ShapeError(
            f"target {tuple(target.shape)}, source {tuple(source.shape)} and depth {tuple(depth.shape)} disagree"
        )
    if (target.shape[-1], target.shape[-2]) != camera.size:
        raise ShapeError(
            f"images are {target.shape[-1]}x{target.shape[-2]}, the camera {camera.width}x{camera.height}"
        )
    cands = init.double()
    if cands.dim() == 3:
        cands = cands[:, None]
    check_shape(cands, f"{target.shape[0]},K,4,4", "init")
    wrap = camera.wraps if wrap is None else wrap
    levels = pyramid(target, source, depth, camera, wrap, config.levels, checked_mask(mask, target))
    starts = [cands[:, i] for i in range(cands.shape[1])]
    pose = starts[0]
    start = torch.zeros(target.shape[0], dtype=torch.long, device=target.device)
    for n, lv in enumerate(reversed(levels)):
        options = starts if n == 0 else [pose, *starts]
        pose, which, cost, res, jac, k = _pick(lv, options)
        start = which if n == 0 else torch.where(which == 0, start, which - 1)
        pose, cost, res = _lm(lv, pose, res, jac, cost, k, config)
    k = robust_scale(res)
    cost = robust_cost(res, k)
    start_cost = robust_cost(residuals(levels[0], starts[0])[0], k)
    keep = start_cost < cost  # only possible across levels: the finest level's own steps never raise it
    pose = torch.where(keep.reshape(-1, 1, 1), starts[0], pose)
    start = torch.where(keep, torch.zeros_like(start), start)
    cost = torch.minimum(cost, start_cost)
    valid = res.valid.flatten(1).float().mean(1)
    return AlignResult(pose, cost, start_cost, start, valid)
