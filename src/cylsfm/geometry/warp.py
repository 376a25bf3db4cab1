"""View synthesis by inverse warping, with horizontal wrap-around for full panoramas."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError, ShapeError, check_shape
from .cameras import Camera
from .seam import circular_pad, resize_image

__all__ = ["inverse_warp", "resize_image", "sample_image", "transform_points"]  # resize_image: from .seam

_SLACK = 1e-3


def transform_points(transform: Tensor, points: Tensor) -> Tensor:
    """Apply rigid transforms ``[B,4,4]`` to point maps ``[B,3,H,W]`` -> ``[B,3,H,W]``."""
    b, _, h, w = points.shape
    rot = transform[:, :3, :3].to(points.dtype)
    t = transform[:, :3, 3:4].to(points.dtype)
    out = torch.baddbmm(t, rot, points.reshape(b, 3, h * w))
    return out.reshape(b, 3, h, w)


def sample_image(image: Tensor, uv: Tensor, wrap: bool) -> tuple[Tensor, Tensor]:
    """Bilinearly sample ``image [B,C,H,W]`` at pixel coordinates ``uv [B,2,Ho,Wo]``.

    ``uv`` uses the pixel-centre convention (integer values at pixel centres). With ``wrap`` the columns
    are periodic: ``u`` is taken modulo ``W`` and a sample between column ``W-1`` and column ``0`` blends
    those two columns. A sample is valid when ``0 <= v <= H-1`` and, without ``wrap``, ``0 <= u <= W-1`` (to 1e-3 px)
    (it needs all four neighbours inside the image). Returns ``(sampled [B,C,Ho,Wo], valid [B,1,Ho,Wo])``;
    invalid samples are 0.
    """
    _, _, h, w = image.shape
    u, v = uv[:, 0], uv[:, 1]
    # A thousandth of a pixel of slack keeps the border rows valid despite float rounding.
    valid = (v >= -_SLACK) & (v <= h - 1 + _SLACK)
    if wrap:
        # One extra column on each side makes every bilinear footprint of u in [0, W) lie inside the
        # padded image: padded column j+1 is image column j, padded 0 is column W-1, padded W+1 is 0.
        padded = circular_pad(image, 1, 1)
        u = torch.remainder(u, w) + 1
        span_u = w + 1  # padded width - 1
    else:
        padded = image
        valid = valid & (u >= -_SLACK) & (u <= w - 1 + _SLACK)
        span_u = max(w - 1, 1)
    gx = u * (2.0 / span_u) - 1
    gy = v * (2.0 / max(h - 1, 1)) - 1
    grid = torch.stack((gx, gy), -1).to(image.dtype)
    sampled = F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=True)
    valid = valid.unsqueeze(1)
    return sampled * valid.to(sampled.dtype), valid


def inverse_warp(
    src_image: Tensor,
    tgt_depth: Tensor,
    T_tgt_to_src: Tensor,
    camera: Camera,
    wrap: bool | None = None,
) -> tuple[Tensor, Tensor]:
    """Synthesise the target view from a source image.

    Each target pixel is lifted with its depth (``camera.unproject``), moved into the source camera by
    ``T_tgt_to_src``, projected (``camera.project``) and the source image is sampled there bilinearly.

    Args:
        src_image: ``[B,C,H,W]`` source image.
        tgt_depth: ``[B,1,H,W]`` target depth in the camera model's depth (cylindrical: horizontal
            distance; pinhole: z), metres or any consistent unit; values ``<= 0`` are invalid.
        T_tgt_to_src: ``[B,4,4]`` rigid transform mapping target-camera points to source-camera points,
            in the depth's unit (``relative_pose(c2w_target, c2w_source)`` for ground-truth poses).
        camera: the camera of both images (image size ``W x H``).
        wrap: sample across the left/right seam; ``None`` means "if the camera wraps" (a full 360 degree
            cylindrical panorama). ``True`` on a camera that does not wrap is an error.

    Returns:
        ``(warped [B,C,H,W], valid [B,1,H,W] bool)``: ``warped`` is 0 where ``valid`` is false (sample
        outside the image vertically, or horizontally without wrap, point not projectable, or depth
        ``<= 0``).

    A camera turned by a quarter of a turn sees the panorama rolled by a quarter of its width, across
    the seam:

    >>> from cylsfm.geometry import CylindricalCamera, roll_columns, yaw_matrix
    >>> cam = CylindricalCamera.full(8, 2)
    >>> image = torch.arange(16.0).reshape(1, 1, 2, 8)
    >>> turn = torch.eye(4).unsqueeze(0)
    >>> turn[0, :3, :3] = yaw_matrix(torch.pi / 2)
    >>> warped, valid = inverse_warp(image, torch.ones(1, 1, 2, 8), turn, cam)
    >>> torch.allclose(warped, roll_columns(image, -2), atol=1e-4), bool(valid.all())
    (True, True)
    """
    check_shape(src_image, "B,C,H,W", "src_image")
    check_shape(tgt_depth, "B,1,H,W", "tgt_depth")
    if src_image.shape[-2:] != tgt_depth.shape[-2:] or src_image.shape[0] != tgt_depth.shape[0]:
        raise ShapeError(
            f"src_image {tuple(src_image.shape)} and tgt_depth {tuple(tgt_depth.shape)} differ in batch or size"
        )
    check_shape(T_tgt_to_src, f"{src_image.shape[0]},4,4", "T_tgt_to_src")
    if wrap is None:
        wrap = camera.wraps
    elif wrap and not camera.wraps:
        raise InputError("wrap=True needs a full 360-degree cylindrical camera (fx * 2 pi == width)")
    # Geometry runs in float32 even under autocast: half precision cannot place a point 80 m away to a
    # fraction of a pixel.
    with torch.autocast(device_type=src_image.device.type, enabled=False):
        depth = tgt_depth.float()
        points = transform_points(T_tgt_to_src.float(), camera.unproject(depth))
        uv = camera.project(points)
        warped, valid = sample_image(src_image.float(), uv, wrap)
        valid = valid & camera.projectable(points) & (depth > 0)
        warped = warped * valid.to(warped.dtype)
    return warped.to(src_image.dtype), valid
