"""Data augmentation of training samples: mirror and colour jitter.

Every frame of a sample gets the same transformation, so that view synthesis between them stays
consistent, and the ground truth (depth, mask, relative poses) and the camera are transformed with the
images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError
from ..geometry import Camera

__all__ = ["AugmentConfig", "augment_geometry", "to_float"]

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
        mirror_prob: probability of a flip.
        color_jitter: random brightness, contrast, saturation and hue, the same for all frames.
        brightness: factor drawn in ``[1 - b, 1 + b]``.
        contrast: factor drawn in ``[1 - c, 1 + c]`` (about the sample's mean grey level).
        saturation: factor drawn in ``[1 - s, 1 + s]``.
        hue: rotation of the chroma (YIQ) plane by up to ``+-hue`` of a full turn.

    Raises:
        InputError: for a probability outside ``[0, 1]``, a jitter strength outside ``[0, 1]`` or a hue
            outside ``[0, 0.5]``.
    """

    mirror: bool = True
    mirror_prob: float = 0.5
    color_jitter: bool = True
    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.05

    def __post_init__(self) -> None:
        if not 0 <= self.mirror_prob <= 1:
            raise InputError(f"mirror_prob must be in [0, 1], got {self.mirror_prob}")
        for name in ("brightness", "contrast", "saturation"):
            value = getattr(self, name)
            if not 0 <= value <= 1:
                raise InputError(f"{name} must be in [0, 1], got {value}")
        if not 0 <= self.hue <= 0.5:
            raise InputError(f"hue must be in [0, 0.5] (a fraction of a turn), got {self.hue}")


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
    """Mirror a sample at random, with its ground truth.

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
    if cfg.mirror and float(torch.rand(())) < cfg.mirror_prob:
        frames = frames.flip(2)
        depth = None if depth is None else depth.flip(-1)
        mask = None if mask is None else mask.flip(-1)
        camera = replace(camera, cx=(camera.width - 1) - camera.cx)
        if pose_gt is not None:
            pose_gt = _MIRROR @ pose_gt @ _MIRROR
    return frames, camera, depth, mask, pose_gt


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
