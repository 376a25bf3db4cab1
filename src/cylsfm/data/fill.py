"""Filling the pixels under a mask from their surroundings, so that a network never sees an occluder fixed
to the camera (a helmet, a mount, a car's roof).

Pull-push: the visible pixels are averaged down an image pyramid (each level halves the size; a pixel's
weight is the fraction of its area that was seen, saturating at 1), then every level is blended up into the
next finer one where that one saw too little. A masked region gets a smooth fill of the colours around it;
seen pixels are returned unchanged.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import ShapeError, check_shape

__all__ = ["fill_masked"]


def _down(x: Tensor) -> Tensor:
    h, w = x.shape[-2:]
    return F.interpolate(x, size=((h + 1) // 2, (w + 1) // 2), mode="area")


def fill_masked(images: Tensor, mask: Tensor) -> Tensor:
    """``images`` with the pixels where ``mask`` is 0 filled smoothly from the pixels around them.

    Args:
        images: ``[B,C,H,W]`` (any range).
        mask: ``[B,1,H,W]`` or ``[1,1,H,W]``: 1 (True) where the pixel is kept, 0 where it is filled.

    Returns:
        ``[B,C,H,W]`` in the dtype of ``images``; equal to ``images`` where ``mask`` is 1. An image with no
        pixel to keep is filled with zeros.

    >>> x = torch.arange(8.0).reshape(1, 1, 1, 8).repeat(1, 1, 2, 1)
    >>> m = torch.ones(1, 1, 2, 8); m[..., 3:5] = 0
    >>> y = fill_masked(x, m)
    >>> bool(torch.equal(y[..., :3], x[..., :3])), 2.0 < float(y[0, 0, 0, 3]) < 6.0
    (True, True)
    """
    check_shape(images, "B,C,H,W", "images")
    check_shape(mask, "N,1,H,W", "mask")
    if mask.shape[-2:] != images.shape[-2:] or mask.shape[0] not in (1, images.shape[0]):
        raise ShapeError(f"mask {tuple(mask.shape)} does not fit images {tuple(images.shape)}")
    x = images.float()
    w = mask.to(device=x.device, dtype=torch.float32).expand(x.shape[0], 1, -1, -1)
    if bool((w >= 1).all()):
        return images
    colours, weights = [x * (w > 0)], [w]
    while min(colours[-1].shape[-2:]) > 1:
        cw = _down(colours[-1] * weights[-1])
        wd = _down(weights[-1])
        colours.append(cw / wd.clamp(min=1e-12))
        weights.append((4 * wd).clamp(max=1))
    out = colours[-1] * (weights[-1] > 0)
    for c, wl in zip(reversed(colours[:-1]), reversed(weights[:-1]), strict=True):
        up = F.interpolate(out, size=c.shape[-2:], mode="bilinear", align_corners=False)
        out = wl * c + (1 - wl) * up
    keep = w >= 1
    return torch.where(keep, x, out).to(images.dtype)
