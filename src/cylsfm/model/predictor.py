"""Running trained networks on images of any size: depth maps and relative poses.

:class:`Predictor` takes images at their own resolution with their camera, brings them to the network's
input (the centred crop of the field of view it was trained on, resized with area averaging), runs the
networks, and brings depth back to the input's resolution. Depth and translation share the network's
unknown scale.

A pose network that reads the motion from frame pairs (the antisymmetric pair network of the default
recipe) is applied more than once (``pose_iterations``): each source is warped into the target's view by
the current pose with the depth network's depth of the target, the pose network reads what motion is
left between the target and that warped source, and the two are composed (the current pose, then the
step read in the target's frame). It is the pose network's own
reading of a smaller residual motion: nothing is optimised and no photometric cost is evaluated
(RESULTS.md, "The pose network applied again to its own warp").
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import Tensor

from ..data.fill import fill_masked
from ..errors import CylsfmError
from ..geometry import (
    Camera,
    CylindricalCamera,
    inverse_warp,
    pose_vec_to_mat,
    resize_image,
    roll_columns,
    roll_pose,
)
from ..runtime import pick_device
from .build import LoadedModels, load_models

__all__ = ["DEFAULT_POSE_ITERATIONS", "Predictor"]

#: Passes of a pair pose network over its own warp after the first (chosen by measurement, RESULTS.md).
DEFAULT_POSE_ITERATIONS = 3


class Predictor:
    """Depth and pose inference with the networks of a checkpoint.

    Args:
        models: networks loaded with :func:`cylsfm.model.load_models`.
        device: where to run them.
        pose_iterations: passes of the pose network over the sources warped by its current pose, after
            the first (see the module docstring); ``None``: :data:`DEFAULT_POSE_ITERATIONS` for a pair pose
            network (``antisymmetric``), 0 for the paper's one-pass network, whose per-slot prior would
            add its usual step again at every pass.

    Raises:
        CylsfmError: ``pose_iterations`` negative, or positive for a one-pass pose network.
    """

    def __init__(
        self, models: LoadedModels, device: torch.device | str = "cpu", pose_iterations: int | None = None
    ) -> None:
        self.models = models
        self.device = torch.device(device)
        self.config = models.config
        self.size = (models.config.data.width, models.config.data.height)
        self.fov = models.config.data.fov
        self.wrap = models.config.wrap
        pairs = bool(models.pose_net.pairs)
        if pose_iterations is None:
            pose_iterations = DEFAULT_POSE_ITERATIONS if pairs else 0
        if pose_iterations < 0:
            raise CylsfmError(f"pose iterations must be >= 0, got {pose_iterations}")
        if pose_iterations and not pairs:
            raise CylsfmError(
                "pose iterations need a pose network that reads frame pairs (model.antisymmetric); this "
                "checkpoint's one-pass network would add its per-slot prior at every pass"
            )
        self.pose_iterations = pose_iterations

    @classmethod
    def from_checkpoint(
        cls, path: str | os.PathLike[str], device: str = "auto", pose_iterations: int | None = None
    ) -> Predictor:
        dev = pick_device(device)
        return cls(load_models(path, dev), dev, pose_iterations)

    # ------------------------------------------------------------------ input preparation
    # The network was trained on panoramas resized to ``config.data.width x height`` and, for a field of
    # view under 360 degrees, on the centred crop of that many degrees of them.
    def window(self, camera: Camera) -> tuple[int, int] | None:
        """Columns ``[x0, x1)`` of the input that the network sees (``None``: all of them)."""
        if self.fov >= 360:
            return None
        if not isinstance(camera, CylindricalCamera) or not camera.wraps:
            raise CylsfmError(
                f"this model was trained on {self.fov:g}-degree crops of full cylindrical panoramas; "
                f"give it full panoramas"
            )
        return camera.crop_window(self.fov)

    def network_camera(self, camera: Camera) -> Camera:
        """The camera of the network's input for input images of ``camera``."""
        cam = camera.resized(*self.size)
        return cam.crop(self.fov) if self.fov < 360 else cam  # type: ignore[attr-defined]

    def prepare(self, images: Tensor, camera: Camera, mask: Tensor | None = None) -> Tensor:
        """``[B,3,H,W]`` in [0, 1] at the camera's size -> the network's input ``[B,3,h,w]``.

        ``mask`` ``[B or 1,1,H,W]``: 1 where the scene is seen, 0 on an occluder fixed to the camera (a
        helmet, a mount), whose pixels the network sees filled from their surroundings
        (:func:`~cylsfm.data.fill.fill_masked`), as in training with a mask; ``None``: the images as they
        are."""
        if images.shape[-2:] != (camera.height, camera.width):
            raise CylsfmError(
                f"images are {images.shape[-1]}x{images.shape[-2]} but the camera is {camera.width}x{camera.height}"
            )
        if mask is not None:
            images = fill_masked(images, mask.to(images.device))
        w, h = self.size
        if images.shape[-2:] != (h, w):
            images = F.interpolate(images, size=(h, w), mode="area")
        if self.fov < 360:
            x0, x1 = self.window(camera.resized(w, h))  # type: ignore[misc]
            images = images[..., x0:x1]
        return images.to(self.device).contiguous(memory_format=torch.channels_last)

    # ------------------------------------------------------------------ outputs
    @torch.inference_mode()
    def disparity(self, images: Tensor, camera: Camera, mask: Tensor | None = None) -> Tensor:
        """Finest-scale disparity ``[B,1,h,w]`` at the network's input size (``mask``: see
        :meth:`prepare`)."""
        return self.models.disp_net(self.prepare(images, camera, mask))[0].float()

    @torch.inference_mode()
    def depth(self, images: Tensor, camera: Camera, mask: Tensor | None = None) -> Tensor:
        """Depth ``[B,1,H,W']`` (network units) at the input's resolution (``W'``: the cropped width).

        The disparity is resized bilinearly (wrapping around the seam of full panoramas) before it is
        inverted, as in SfMLearner's evaluation. ``mask``: see :meth:`prepare` (the depth under the
        occluder is the filled image's: meaningless; leave it out downstream).
        """
        disp = self.disparity(images, camera, mask)
        win = self.window(camera)  # the same field of view at the input's resolution
        width = camera.width if win is None else win[1] - win[0]
        size = (camera.height, width)
        wrap = self.wrap and camera.wraps and win is None
        if disp.shape[-2:] != size:
            if wrap and width % disp.shape[-1] == 0:
                disp = resize_image(disp, size, wrap=True)
            else:
                disp = F.interpolate(disp, size=size, mode="bilinear", align_corners=False)
        return 1.0 / disp.clamp(min=1e-6)

    @torch.inference_mode()
    def poses(
        self, target: Tensor, sources: Tensor, camera: Camera, roll: int = 0, mask: Tensor | None = None
    ) -> Tensor:
        """Relative poses ``T_tgt_to_src [B,S,4,4]`` (translation in network depth units).

        ``target`` is ``[B,3,H,W]``, ``sources`` ``[B,S,3,H,W]`` with ``S = seq_length - 1`` of the model.

        With :attr:`pose_iterations` the pose network then reads the motion left between the target and
        each source warped by the pose so far, that many times (see the module docstring).

        ``roll`` (full panoramas only): the network reads the frames rolled by this many columns of its
        input (a yaw, :func:`~cylsfm.geometry.roll_columns`) and its poses are turned back
        (:func:`~cylsfm.geometry.roll_pose`): e.g. to show it a camera mounted turned as one that faces its
        motion (:func:`cylsfm.odometry.mount.mount_yaw`). ``mask``: see :meth:`prepare`.

        Raises:
            CylsfmError: ``roll`` for a model that does not see whole panoramas.
        """
        if roll and not (self.fov >= 360 and self.wrap):
            raise CylsfmError("turning the frames (roll) needs a model of full panoramas")
        b, s = sources.shape[:2]
        tgt = self.prepare(target, camera, mask)
        src = self.prepare(sources.flatten(0, 1), camera, mask).reshape(b, s, *tgt.shape[1:])
        if roll:
            tgt = roll_columns(tgt, roll).contiguous(memory_format=torch.channels_last)
            src = roll_columns(src, roll)
        pose = pose_vec_to_mat(self.models.pose_net(tgt, src)[0].double())
        if self.pose_iterations:
            pose = self._iterate(tgt, src, pose, self.network_camera(camera))
        return roll_pose(pose, -roll, tgt.shape[-1]) if roll else pose

    def _iterate(self, tgt: Tensor, src: Tensor, pose: Tensor, camera: Camera) -> Tensor:
        """Refine ``pose [B,S,4,4]`` (float64, ``T_tgt_to_src``) of the network inputs ``tgt [B,3,h,w]``,
        ``src [B,S,3,h,w]`` (``camera``: theirs) by :attr:`pose_iterations` further passes of the pose
        network: each reads the target and every source warped into the target's view by the current pose
        with the target's predicted depth (the target's own pixels where the warp leaves the source).

        The warped source is the view of a virtual camera ``V`` whose pixels see, with the target's depth,
        what the source sees through the current pose: ``T_tgt_to_V = T_cur^-1 T_true``. The network reads
        that step, so the pose is ``T_cur @ step`` (the step is applied in the target's frame, before the
        current pose; for pure yaws, which commute, the order would not show)."""
        b, s = src.shape[:2]
        depth = 1.0 / self.models.disp_net(tgt)[0].float().clamp(min=1e-6)
        depth, target = depth.repeat_interleave(s, 0), tgt.float().repeat_interleave(s, 0)
        flat = src.flatten(0, 1).float()
        for _ in range(self.pose_iterations):
            warped, valid = inverse_warp(flat, depth, pose.flatten(0, 1).float(), camera)
            warped = torch.where(valid.expand_as(warped), warped, target).to(src.dtype)
            step = self.models.pose_net(tgt, warped.view(b, s, *warped.shape[1:]))[0]
            pose = pose @ pose_vec_to_mat(step.double())
        return pose
