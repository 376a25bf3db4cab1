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

Precision (``amp``, on by default): where bf16 is native (CUDA GPUs that have it, CPUs with AVX-512 BF16 or
AMX: :func:`cylsfm.runtime.autocast_dtype`) the networks run in bf16 (copies of their weights cast once; on
a CUDA GPU without bf16, fp16 autocast); everything else (the visual compass, the warps, depth from
disparity) stays in fp32 and the outputs are fp32. Elsewhere, or with ``amp=False``, all in fp32.
"""

from __future__ import annotations

import contextlib
import copy
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
    window_yaws,
)
from ..runtime import autocast_dtype, network_precision, pick_device, prefers_channels_last
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
        amp: the networks in bf16 where it is native (see the module docstring); ``False``: fp32.

    Raises:
        CylsfmError: ``pose_iterations`` negative, or positive for a one-pass pose network.
    """

    def __init__(
        self,
        models: LoadedModels,
        device: torch.device | str = "cpu",
        pose_iterations: int | None = None,
        amp: bool = True,
    ) -> None:
        self.models = models
        self.device = torch.device(device)
        #: the dtype the networks run in (``None``: fp32)
        self.dtype = autocast_dtype(self.device, amp)
        self.disp_net, self.pose_net = models.disp_net, models.pose_net
        # copies cast once (autocast would cast every weight again at each call) and, where convolutions
        # are faster so (AVX-512 CPUs, GPUs: runtime.prefers_channels_last), in channels-last memory, as
        # the trainer keeps them: depth 0.66-0.81x the time of contiguous weights (BENCHMARKS.md)
        bf16 = self.dtype == torch.bfloat16
        fmt = torch.channels_last if prefers_channels_last(self.device) else None
        if bf16 or fmt is not None:
            self.disp_net = _inference_copy(models.disp_net, bf16, fmt)
            self.pose_net = _inference_copy(models.pose_net, bf16, fmt)
        self.config = models.config
        #: the network's input size ``(W, H)`` in pixels (a crop's full turn for a model of crops)
        self.size = (models.config.data.width, models.config.data.height)
        #: the horizontal field of view (degrees) the networks see
        self.fov = models.config.data.fov
        #: whether the networks' convolutions wrap around the seam
        self.wrap = models.config.wrap
        #: frames the pose network reads at once: a target with ``(window_length - 1) // 2`` sources on
        #: each side
        self.window_length = int(models.config.data.seq_length)
        #: frames between two of a window's frames in training (the spacing of the steps it learned)
        self.frame_stride = int(models.config.data.stride)
        #: rows of the training panoramas span ``h`` in ``[-vfov_h, vfov_h]`` (the run's measurement,
        #: :func:`cylsfm.model.build.training_vfov_h`): what the networks expect of a panorama's rows
        self.vfov_h = models.vfov_h
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
        cls,
        path: str | os.PathLike[str],
        device: str = "auto",
        pose_iterations: int | None = None,
        amp: bool = True,
    ) -> Predictor:
        dev = pick_device(device)
        return cls(load_models(path, dev), dev, pose_iterations, amp)

    def _precision(self) -> contextlib.AbstractContextManager:
        """fp16 autocast (a CUDA GPU without bf16); nothing for bf16 (the networks are bf16 copies) or fp32."""
        return network_precision(self.device, self.dtype if self.dtype == torch.float16 else None)

    def _disparity(self, images: Tensor) -> Tensor:
        """The depth network's finest disparity ``[B,1,h,w]`` (fp32) of network inputs ``[B,3,h,w]``."""
        with self._precision():
            return self.disp_net(images)[0].float()

    def _pose(self, target: Tensor, sources: Tensor) -> Tensor:
        """The pose network's ``[B,S,6]`` (fp32) of network inputs; the compass's yaw (if the model has
        it) read from the fp32 images."""
        with self._precision():
            vec, _ = self.pose_net.net(target, sources)
        return self.pose_net.with_compass(vec.float(), target, sources)

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
        return self._disparity(self.prepare(images, camera, mask))

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
        self,
        target: Tensor,
        sources: Tensor,
        camera: Camera,
        roll: int = 0,
        mask: Tensor | None = None,
        depth: Tensor | None = None,
    ) -> Tensor:
        """Relative poses ``T_tgt_to_src [B,S,4,4]`` (translation in network depth units).

        ``target`` is ``[B,3,H,W]``, ``sources`` ``[B,S,3,H,W]`` with ``S = seq_length - 1`` of the model.

        With :attr:`pose_iterations` the pose network then reads the motion left between the target and
        each source warped by the pose so far, that many times (see the module docstring).

        ``roll`` (full panoramas only): the network reads the frames rolled by this many columns of its
        input (a yaw, :func:`~cylsfm.geometry.roll_columns`) and its poses are turned back
        (:func:`~cylsfm.geometry.roll_pose`): e.g. to show it a camera mounted turned as one that faces its
        motion (:func:`cylsfm.odometry.mount.mount_yaw`). ``mask``: see :meth:`prepare`.

        ``depth``: the targets' depth ``[B,1,h,w]`` at the network's input size (of the frames as given,
        not rolled; e.g. :meth:`depth` of network-size frames), which the further passes then use instead
        of predicting it again; ``None``: predicted here (once per call).

        Raises:
            CylsfmError: ``roll`` for a model that does not see whole panoramas; ``depth`` of another size.
        """
        self._check_roll(roll)
        b, s = sources.shape[:2]
        tgt = self.prepare(target, camera, mask)
        src = self.prepare(sources.flatten(0, 1), camera, mask).reshape(b, s, *tgt.shape[1:])
        if roll:
            tgt = roll_columns(tgt, roll).contiguous(memory_format=torch.channels_last)
            src = roll_columns(src, roll)
        pose = pose_vec_to_mat(self._pose(tgt, src).double())
        return self._further(tgt, src, pose, camera, roll, depth)

    @torch.inference_mode()
    def ride_poses(
        self,
        frames: Tensor,
        camera: Camera,
        roll: int = 0,
        mask: Tensor | None = None,
        depth: Tensor | None = None,
    ) -> Tensor:
        """The poses of every window of ``S + 1`` consecutive frames (a target and ``S/2`` frames either
        side, ``S = seq_length - 1`` of the model, even) of ``frames [N,3,H,W]``: ``T_tgt_to_src
        [N-S,S,4,4]``, window ``c`` with target ``c + S/2``, as :meth:`poses` gives for those windows (up
        to float rounding), with each frame prepared once, its compass spectrum computed once and each pair
        of frames read once by the pose network's first pass (the pair network's pose from ``b`` to ``a``
        is the negated 6-vector of the pose from ``a`` to ``b``; the further passes are each window's own).

        ``roll``: as for :meth:`poses`; ``mask``: ``[N or 1,1,H,W]`` (see :meth:`prepare`); ``depth``: the
        targets' depth ``[N-S,1,h,w]`` at the network's input size (``None``: predicted here).

        A one-pass pose network (the paper's) reads each window whole, as :meth:`poses` does.

        Raises:
            CylsfmError: an odd ``S``, fewer than ``S + 1`` frames, or as :meth:`poses`.
        """
        s = self.pose_net.n_sources
        if s % 2:
            raise CylsfmError(f"ride_poses needs windows centred on their target, not {s} sources")
        n, k = frames.shape[0], s // 2
        if n < s + 1:
            raise CylsfmError(f"ride_poses needs at least {s + 1} frames, got {n}")
        if not self.pose_net.pairs:  # a one-pass network reads each window whole
            tgt = frames[k : n - k]
            src = torch.stack([frames[k + o : n - k + o] for o in range(-k, k + 1) if o], 1)
            return self.poses(tgt, src, camera, roll, mask, depth)
        self._check_roll(roll)
        x = self.prepare(frames, camera, mask)
        if roll:
            x = roll_columns(x, roll).contiguous(memory_format=torch.channels_last)
        m = n - s
        firsts = torch.cat([x[: n - d] for d in range(1, k + 1)])
        seconds = torch.cat([x[d:] for d in range(1, k + 1)])
        with self._precision():
            vecs = self.pose_net.net.pair_vectors(firsts, seconds)  # v(a -> a + d), d = 1 .. k in turn
        ahead = dict(zip(range(1, k + 1), vecs.split([n - d for d in range(1, k + 1)]), strict=True))
        tgt = x[k : k + m]
        offsets = [o for o in range(-k, k + 1) if o]
        src = torch.stack([x[k + o : k + o + m] for o in offsets], 1)  # [m,S,3,h,w], laid out as poses' are:
        src = src.flatten(0, 1).contiguous(memory_format=torch.channels_last).view(src.shape)
        vec = torch.stack(
            [ahead[o][k : k + m] if o > 0 else -ahead[-o][k + o : k + o + m] for o in offsets], 1
        )
        yaws = window_yaws(x.float(), k) if self.pose_net.compass is not None else None
        vec = self.pose_net.with_compass(vec.float(), tgt, src, yaws)
        return self._further(tgt, src, pose_vec_to_mat(vec.double()), camera, roll, depth)

    def _check_roll(self, roll: int) -> None:
        if roll and not (self.fov >= 360 and self.wrap):
            raise CylsfmError("turning the frames (roll) needs a model of full panoramas")

    def _further(
        self, tgt: Tensor, src: Tensor, pose: Tensor, camera: Camera, roll: int, depth: Tensor | None
    ) -> Tensor:
        """The further passes over the first pass's ``pose [B,S,4,4]`` of the (rolled) network inputs, and
        the poses turned back by ``roll`` (see :meth:`poses`)."""
        b = tgt.shape[0]
        if self.pose_iterations:
            if depth is not None:
                if depth.shape != (b, 1, *tgt.shape[-2:]):
                    raise CylsfmError(
                        f"depth {tuple(depth.shape)} does not fit the network's input {tuple(tgt.shape)}"
                    )
                depth = roll_columns(depth.to(self.device).float(), roll) if roll else depth.to(self.device)
            pose = self._iterate(tgt, src, pose, self.network_camera(camera), depth)
        return roll_pose(pose, -roll, tgt.shape[-1]) if roll else pose

    def _iterate(
        self, tgt: Tensor, src: Tensor, pose: Tensor, camera: Camera, depth: Tensor | None = None
    ) -> Tensor:
        """Refine ``pose [B,S,4,4]`` (float64, ``T_tgt_to_src``) of the network inputs ``tgt [B,3,h,w]``,
        ``src [B,S,3,h,w]`` (``camera``: theirs) by :attr:`pose_iterations` further passes of the pose
        network: each reads the target and every source warped into the target's view by the current pose
        with the target's depth (``depth [B,1,h,w]``, or predicted here) (the target's own pixels where the
        warp leaves the source).

        The warped source is the view of a virtual camera ``V`` whose pixels see, with the target's depth,
        what the source sees through the current pose: ``T_tgt_to_V = T_cur^-1 T_true``. The network reads
        that step, so the pose is ``T_cur @ step`` (the step is applied in the target's frame, before the
        current pose; for pure yaws, which commute, the order would not show)."""
        b, s = src.shape[:2]
        if depth is None:
            depth = 1.0 / self._disparity(tgt).clamp(min=1e-6)
        depth, target = depth.repeat_interleave(s, 0), tgt.float().repeat_interleave(s, 0)
        flat = src.flatten(0, 1).float()
        for _ in range(self.pose_iterations):
            warped, valid = inverse_warp(flat, depth, pose.flatten(0, 1).float(), camera)
            warped = torch.where(valid.expand_as(warped), warped, target).to(src.dtype)
            step = self._pose(tgt, warped.view(b, s, *warped.shape[1:]))
            pose = pose @ pose_vec_to_mat(step.double())
        return pose


def _inference_copy(net: torch.nn.Module, bf16: bool, fmt: torch.memory_format | None) -> torch.nn.Module:
    """A copy of ``net`` in bf16 (``bf16``) and in memory format ``fmt`` (``None``: as it is)."""
    net = copy.deepcopy(net)
    if bf16:
        net = net.to(torch.bfloat16)
    return net.to(memory_format=fmt) if fmt is not None else net
