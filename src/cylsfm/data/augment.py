"""Data augmentation of training samples: time reversal, yaw roll, mirror and colour jitter.

Every frame of a sample gets the same transformation, so that view synthesis between them stays
consistent, and the ground truth (depth, mask, relative poses) and the camera are transformed with the
images. The roll turns the panoramas about the vertical axis through :mod:`cylsfm.geometry.seam`
(:func:`~cylsfm.geometry.seam.roll_columns`, :func:`~cylsfm.geometry.seam.roll_pose`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError
from ..geometry import Camera
from ..geometry.seam import roll_columns, roll_pose

__all__ = ["AugmentConfig", "augment_geometry", "check_rollable", "to_float"]

_MIRROR = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=torch.float64))
_GREY = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
_RGB_TO_YIQ = torch.tensor(
    [[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=torch.float64
)
_YIQ_TO_RGB = torch.linalg.inv(_RGB_TO_YIQ)


@dataclass(frozen=True)
class AugmentConfig:
    """Data augmentation of training samples. Every frame of a sample gets the same transformation, so
    that view synthesis between them stays consistent; ground truth is transformed with the images.

    Attributes:
        mirror: horizontal flip of all frames with probability ``mirror_prob``: column ``u`` goes to
            ``W - 1 - u`` and the camera becomes ``cx' = (W - 1) - cx``. Depth and mask are flipped with the
            frames, and ground-truth relative poses are mirrored ``T' = M T M`` with ``M = diag(-1, 1, 1,
            1)``. With ``cx = W / 2`` the mirrored principal point sits one column to the left, which a
            network that reads azimuth from the column (the yaw-equivariant pose head) does not know.
        mirror_exact: for a full panorama whose ``2 cx`` is a whole number, mirror about the principal
            azimuth instead: column ``u`` goes to ``(2 cx - u) mod W`` (a flip and a roll by one column
            for ``cx = W / 2``) and the camera is unchanged, so that every sample keeps straight ahead at
            the same column. Off by default: at 2000 steps it did not measure better (RESULTS.md).
        mirror_prob: probability of a flip.
        color_jitter: random brightness, contrast, saturation and hue, the same for all frames.
        brightness: factor drawn in ``[1 - b, 1 + b]``.
        contrast: factor drawn in ``[1 - c, 1 + c]`` (about the sample's mean grey level).
        saturation: factor drawn in ``[1 - s, 1 + s]``.
        hue: rotation of the chroma (YIQ) plane by up to ``+-hue`` of a full turn.
        roll: roll all frames horizontally by a random number ``k`` of columns (uniform in ``[0, W)``):
            a yaw rotation of the camera by ``2 pi k / W``. Depth and mask are rolled, and ground-truth
            relative poses conjugated with ``yaw_matrix(2 pi k / W)``. Only for full 360° panoramas
            (cameras that wrap). **Off by default**: the paper's pose network ends in a spatial average,
            which is invariant to rolls, so it cannot predict the rotated ego-motion; in a prototype,
            rolling made ego-motion unlearnable. It is meant for a yaw-equivariant pose network.
        reverse: play the snippet backwards with probability ``reverse_prob``: the sources swap places
            (the frame after the target comes first) and so do their ground-truth poses. The target and
            its depth are unchanged. Without it every sample moves forward and the pose network can
            predict "the first source is one step back" from the source's slot alone, without reading
            the motion from the images; with it the slot says nothing.
        reverse_prob: probability of a reversal.
        still: probability that the sample becomes a camera standing still: every source replaced by
            the target (ground-truth poses: the identity). Without such samples a network trained on rides
            that always move learns the usual step as a prior and predicts it for a camera that does not
            move; the trainer asks for zero motion on them (``loss.still_weight``).

    Raises:
        InputError: for a probability outside ``[0, 1]``, a jitter strength outside ``[0, 1]`` or a hue
            outside ``[0, 0.5]``.
    """

    mirror: bool = True
    mirror_prob: float = 0.5
    mirror_exact: bool = False
    color_jitter: bool = True
    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.05
    roll: bool = False
    reverse: bool = False
    reverse_prob: float = 0.5
    still: float = 0.0

    def __post_init__(self) -> None:
        for name in ("mirror_prob", "reverse_prob", "still"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("brightness", "contrast", "saturation"):
            value = getattr(self, name)
            if not 0 <= value <= 1:
                raise InputError(f"{name} must be in [0, 1], got {value}")
        if not 0 <= self.hue <= 0.5:
            raise InputError(f"hue must be in [0, 0.5] (a fraction of a turn), got {self.hue}")


def check_rollable(augment: AugmentConfig | None, cameras: Iterable[tuple[str, Camera]]) -> None:
    """Raise :class:`~cylsfm.errors.InputError` when ``augment`` rolls and a camera does not wrap.

    ``cameras``: ``(what, camera)`` pairs; ``what`` names the camera in the message.
    """
    if augment is None or not augment.roll:
        return
    for what, camera in cameras:
        if not camera.wraps:
            raise InputError(
                "roll augmentation needs full 360-degree panoramas (fx * 2 pi == width); "
                f"{what} does not wrap"
            )


def _color_matrix(cfg: AugmentConfig, mean_grey: float) -> tuple[Tensor, Tensor]:
    """Random colour transform ``x -> A x + t`` (``A [3,3]``, ``t [3]``): brightness, contrast, saturation
    and hue in that order, composed into one affine map."""
    r = torch.rand(4, dtype=torch.float64) * 2 - 1
    b = 1 + cfg.brightness * float(r[0])
    c = 1 + cfg.contrast * float(r[1])
    s = 1 + cfg.saturation * float(r[2])
    angle = 2 * math.pi * cfg.hue * float(r[3])
    sat = s * torch.eye(3, dtype=torch.float64) + (1 - s) * _GREY.expand(3, 3)
    rot = torch.eye(3, dtype=torch.float64)
    rot[1:, 1:] = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    hue = _YIQ_TO_RGB @ rot @ _RGB_TO_YIQ
    a = hue @ sat * (c * b)
    # the contrast pivot is grey, which saturation and hue leave unchanged
    t = torch.full((3,), (1 - c) * b * mean_grey, dtype=torch.float64)
    return a.float(), t.float()


def augment_geometry(
    frames: Tensor,
    camera: Camera,
    depth: Tensor | None,
    mask: Tensor | None,
    pose_gt: Tensor | None,
    cfg: AugmentConfig,
) -> tuple[Tensor, Camera, Tensor | None, Tensor | None, Tensor | None]:
    """Stand still, reverse, roll and mirror a sample at random (in that order), with its ground truth.

    Args:
        frames: ``uint8 [L,H,W,3]``, the target first, then the sources in time order.
        camera: the frames' camera (size ``W x H``).
        depth: target depth ``[1,H,W]`` (metres), or ``None``.
        mask: ``[1,H,W]`` in ``{0, 1}``, or ``None``.
        pose_gt: ``float64 [L-1,4,4]`` ``T_tgt_to_src`` per source, or ``None``.
        cfg: which transformations may be drawn (uses ``torch``'s global random generator).

    Returns:
        ``(frames, camera, depth, mask, pose_gt)`` transformed alike; unchanged inputs are returned as is.
    """
    width = camera.width
    if cfg.still and float(torch.rand(())) < cfg.still:
        frames = frames[:1].expand_as(frames).clone()
        pose_gt = None if pose_gt is None else torch.eye(4, dtype=pose_gt.dtype).expand_as(pose_gt).clone()
    if cfg.reverse and float(torch.rand(())) < cfg.reverse_prob:
        frames = torch.cat([frames[:1], frames[1:].flip(0)])
        pose_gt = None if pose_gt is None else pose_gt.flip(0)
    if cfg.roll:
        k = int(torch.randint(0, width, ()))
        if k:
            frames = roll_columns(frames, k, axis=2)
            depth = None if depth is None else roll_columns(depth, k)
            mask = None if mask is None else roll_columns(mask, k)
            # the content at azimuth theta is now at theta + 2 pi k / W: T' = Y T Y^-1
            pose_gt = None if pose_gt is None else roll_pose(pose_gt, k, width)
    if cfg.mirror and float(torch.rand(())) < cfg.mirror_prob:
        frames = frames.flip(2)
        depth = None if depth is None else depth.flip(-1)
        mask = None if mask is None else mask.flip(-1)
        shift = _mirror_shift(camera) if cfg.mirror_exact else None
        if shift is None:
            camera = replace(camera, cx=(camera.width - 1) - camera.cx)
        elif shift:  # u -> W - 1 - u -> (2 cx - u) mod W: the same camera
            frames = roll_columns(frames, shift, axis=2)
            depth = None if depth is None else roll_columns(depth, shift)
            mask = None if mask is None else roll_columns(mask, shift)
        if pose_gt is not None:
            pose_gt = _MIRROR @ pose_gt @ _MIRROR
    return frames, camera, depth, mask, pose_gt


def _mirror_shift(camera: Camera) -> int | None:
    """The roll (columns) that turns a flip of ``camera``'s frames into the mirror about its principal
    azimuth, ``u -> (2 cx - u) mod W``; ``None`` where the columns do not wrap or ``2 cx`` is not whole."""
    twice = 2.0 * float(camera.cx)
    if not camera.wraps or abs(twice - round(twice)) > 1e-6:
        return None
    return int(round(twice) - camera.width + 1) % int(camera.width)


def to_float(frames: Tensor, cfg: AugmentConfig | None) -> Tensor:
    """``uint8 [L,H,W,3]`` -> ``float32 [L,3,H,W]`` in ``[0, 1]``, colour-jittered (the same for all frames)
    when ``cfg.color_jitter``."""
    x = frames.permute(0, 3, 1, 2).to(dtype=torch.float32, memory_format=torch.contiguous_format)
    if cfg is None or not cfg.color_jitter:
        return x.div_(255.0)
    # the contrast pivot: the sample's mean grey level (a sparse grid of pixels is enough)
    mean_grey = float(x[..., ::4, ::4].mean(dim=(0, 2, 3)).double() @ _GREY) / 255.0
    a, t = _color_matrix(cfg, mean_grey)
    # x -> A x / 255 + t at every pixel: a 1x1 convolution with bias, one fused pass
    return F.conv2d(x, (a / 255.0).view(3, 3, 1, 1), t).clamp_(0, 1)
