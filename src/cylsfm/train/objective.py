"""The training objective: a batch and the networks' outputs -> every loss term, by name.

Read top-down as monodepth2's ``process_batch -> compute_losses``: :func:`batch_on` puts a loader's batch on
the device as a typed :class:`Batch` (images cropped to the field of view, their camera, the pixels to use);
:class:`SfMNet` runs the networks (and, in training, the pair network's scaffold); :class:`Objective`
turns both into the loss terms of :func:`cylsfm.losses.view_synthesis_loss` plus the scaffold's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ..data.dataset import camera_of
from ..data.fill import fill_masked
from ..geometry import Camera, pose_vec_to_mat
from ..losses import LossConfig, dense_depth_term, sfm_pose_term, sparse_depth_term, view_synthesis_loss
from ..nn import DispNet, PoseModel
from .scaffold import SlotPriorScaffold

__all__ = ["Batch", "Objective", "Outputs", "SfMNet", "batch_on"]


@dataclass
class Batch:
    """One training batch on the device.

    Attributes:
        target: ``[B,3,H,W]`` in ``[0, 1]``; ``sources``: ``[B,S,3,H,W]``.
        camera: the images' camera (batched intrinsics).
        mask: ``[B,1,H,W]`` or ``[1,1,H,W]`` weights of the pixels to use, or ``None`` (all).
        sfm: the rides' own adjusted geometry, or ``None``: ``(depth [B,4,H,W], T_tgt_to_src [B,S,4,4],
            step [B,S])`` (:class:`~cylsfm.data.SequenceDataset`'s ``sfm_*`` keys).
    """

    target: Tensor
    sources: Tensor
    camera: Camera
    mask: Tensor | None
    sfm: tuple[Tensor, Tensor, Tensor] | None = None

    def network_inputs(self) -> tuple[Tensor, Tensor]:
        """``(target, sources)`` as the networks see them: the pixels outside the mask (an occluder fixed
        to the camera) filled from their surroundings (:func:`~cylsfm.data.fill.fill_masked`), as at
        inference; the loss compares the images themselves, within the mask."""
        if self.mask is None:
            return self.target, self.sources
        b, s = self.sources.shape[:2]
        tgt = fill_masked(self.target, self.mask)
        per_source = self.mask.repeat_interleave(s, 0) if self.mask.shape[0] == b else self.mask
        src = fill_masked(self.sources.flatten(0, 1), per_source).view_as(self.sources)
        if self.target.is_contiguous(memory_format=torch.channels_last):
            tgt = tgt.contiguous(memory_format=torch.channels_last)
        return tgt, src


def batch_on(sample: dict[str, Any], device: torch.device, fov: float, channels_last: bool) -> Batch:
    """A loader's collated ``sample`` on ``device``, cropped to the centred ``fov`` degrees (the samples'
    masks, augmented with them, included)."""
    tgt = sample["target"].to(device, non_blocking=True)
    src = sample["sources"].to(device, non_blocking=True)
    cam = camera_of(sample)
    mask = sample["mask"].to(device) if "mask" in sample else None
    sfm = None
    if "sfm_depth" in sample:
        sfm = tuple(sample[k].to(device) for k in ("sfm_depth", "sfm_pose", "sfm_step"))
    if fov < 360:
        x0, x1 = cam.index(0).crop_window(fov)
        cam = cam.crop(fov)
        tgt, src = tgt[..., x0:x1], src[..., x0:x1]
        mask = mask[..., x0:x1] if mask is not None else None
        sfm = (sfm[0][..., x0:x1], *sfm[1:]) if sfm is not None else None
    if channels_last:
        tgt = tgt.contiguous(memory_format=torch.channels_last)
    return Batch(tgt, src, cam, mask, sfm)


#: ``(disparities per scale [B,1,H_s,W_s], pose [B,S,6], masks or None, scaffold terms)``.
Outputs = tuple[list[Tensor], Tensor, list[Tensor] | None, dict[str, Tensor]]


class SfMNet(nn.Module):
    """Both networks and the training scaffold in one module (one DistributedDataParallel wrapper, one
    optimiser). The scaffold, when there is one, acts on the pair network's poses before the compass's yaw
    is added."""

    def __init__(self, disp_net: DispNet, scaffold: SlotPriorScaffold | None, pose_net: PoseModel) -> None:
        super().__init__()
        self.disp_net = disp_net
        self.scaffold = scaffold  # registered between the two: the parameters' order of earlier versions
        self.pose_net = pose_net

    def forward(self, target: Tensor, sources: Tensor, step: int) -> Outputs:
        disps = self.disp_net(target)
        pose, masks = self.pose_net.net(target, sources)
        terms: dict[str, Tensor] = {}
        if self.scaffold is not None:
            pose, terms = self.scaffold(pose, step)
        return disps, self.pose_net.with_compass(pose, target, sources), masks, terms


class Objective:
    """The loss of one step: view synthesis (every term of :class:`~cylsfm.losses.LossConfig`), the terms
    of the rides' own adjusted geometry when the batch has it (``sfm_depth``, ``sfm_pose``; the sources
    warped with the adjusted poses with ``sfm_synthesis``) plus the networks' own training terms.

    Args:
        config: the view-synthesis loss's weights and variants.
        wrap: across the seam (full panoramas).
    """

    def __init__(self, config: LossConfig, wrap: bool) -> None:
        self.config, self.wrap = config, wrap

    def __call__(self, batch: Batch, outputs: Outputs) -> tuple[Tensor, dict[str, Tensor], dict[str, Any]]:
        """``(total, terms by name (with "total"), pictures and numbers for the logs)``."""
        disps, pose_vec, masks, extra = outputs
        cfg = self.config
        disps = [d.float() for d in disps]
        masks = [m.float() for m in masks] if masks is not None and cfg.explain_weight > 0 else None
        poses = pose_vec_to_mat(pose_vec.float())
        target = batch.target.float().contiguous()
        warp_poses, own = poses, {}
        if batch.sfm is not None:
            sfm_depth, sfm_pose, step = (t.float() for t in batch.sfm)
            if batch.mask is not None:  # no point on an occluder
                sfm_depth = sfm_depth * (batch.mask > 0.5)
            if cfg.sfm_synthesis:
                warp_poses = torch.where(step[..., None, None] > 0, sfm_pose, poses)
            if cfg.sfm_depth_weight > 0:
                own["sfm_depth"] = cfg.sfm_depth_weight * sparse_depth_term(disps[0], sfm_depth[:, :2])
            if cfg.sfm_dense_weight > 0:
                own["sfm_dense"] = cfg.sfm_dense_weight * dense_depth_term(disps[0], sfm_depth[:, 2:])
            if cfg.sfm_pose_weight > 0:
                own["sfm_pose"] = cfg.sfm_pose_weight * sfm_pose_term(poses, sfm_pose, step)
        out = view_synthesis_loss(
            target,
            batch.sources.float(),
            disps,
            warp_poses,
            batch.camera,
            cfg,
            explainability=masks,
            static_mask=batch.mask,
            wrap=self.wrap,
        )
        total = out.total + sum(own.values()) + sum(extra.values())
        terms = {**out.terms, **own, **extra, "total": total}
        visuals = {
            "target": target[:1].detach(),
            "warped": out.warped[:1] if out.warped is not None else None,
            "error": out.error[:1] if out.error is not None else None,
            "disparity": disps[0][:1].detach(),
            "explainability": masks[0][:1].detach() if masks is not None else None,
            "translation_norm": poses[:, :, :3, 3].norm(dim=-1).mean().detach(),
        }
        return total, terms, visuals
