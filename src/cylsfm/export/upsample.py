"""Depth brought to a finer panorama, guided by its colours (joint bilateral upsampling, Kopf et al. 2007).

A network predicts depth at its own size (256x64 for the demo) while the panorama it came from may be
2048 pixels wide. Interpolating the depth alone blurs every depth edge over a network pixel, so meshes built
from it smear foreground into background. Here every fine pixel ``p`` averages the coarse depths ``D(q)`` of
the 4x4 coarse pixels around it, weighted by

    w(p, q) = exp(-|p - q|^2 / (2 s_s^2)) * exp(-|I(p) - I'(q)|^2 / (2 s_c^2))

(distance in coarse pixels; ``I`` the fine colours in [0, 1], ``I'`` the colours area-averaged to the coarse
grid), so that a fine pixel takes the depth of the coarse neighbours that look like it: depth edges follow
the colour edges of the fine panorama. Columns wrap around the 360-degree seam, rows are clamped. Unknown
depth (0) has no weight; a fine pixel is unknown where most of its spatial weight is.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError

__all__ = ["guided_upsample"]

_TAPS = torch.arange(-1, 3)  # the 4 coarse pixels around a fine pixel's coarse coordinate, along an axis


def _coordinates(fine: int, coarse: int) -> torch.Tensor:
    """Each fine pixel centre in coarse pixels (``u' = (u + 0.5) coarse / fine - 0.5``), ``float64 [fine]``."""
    return (torch.arange(fine, dtype=torch.float64) + 0.5) * (coarse / fine) - 0.5


def _taps(fine: int, coarse: int, sigma: float, wrap: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The coarse neighbours ``int64 [fine,4]`` along one axis and their spatial weights ``float32 [fine,4]``."""
    x = _coordinates(fine, coarse)
    index = torch.floor(x).long()[:, None] + _TAPS[None]
    weight = torch.exp(-((x[:, None] - index) ** 2) / (2 * sigma**2)).float()
    index = index % coarse if wrap else index.clamp(0, coarse - 1)
    return index, weight


def guided_upsample(
    depth: np.ndarray,
    guide: np.ndarray,
    wrap: bool = True,
    sigma_space: float = 0.8,
    sigma_colour: float = 0.1,
    rows_per_chunk: int = 64,
) -> np.ndarray:
    """Depth ``float32 [h,w]`` (0: unknown) upsampled to the size of ``guide`` ``uint8 [H,W,3]``.

    Args:
        depth: the coarse depth; any unit (kept).
        guide: the fine colours of the same field of view (``H >= h``, ``W >= w``).
        wrap: columns wrap around (a full 360-degree panorama).
        sigma_space: the spatial weight's width, in coarse pixels.
        sigma_colour: the colour weight's width, in colour units of [0, 1].
        rows_per_chunk: fine rows computed at once (memory: ``16 x 3`` floats per fine pixel).

    Returns:
        ``float32 [H,W]`` depth, 0 where unknown.
    """
    h, w = depth.shape
    big_h, big_w = guide.shape[:2]
    if guide.ndim != 3 or guide.shape[2] != 3 or big_h < h or big_w < w:
        raise InputError(f"the guide must be a colour image at least {w}x{h}, got shape {guide.shape}")
    fine = torch.from_numpy(np.ascontiguousarray(guide)).float().div(255)  # [H,W,3]
    coarse = F.interpolate(fine.permute(2, 0, 1)[None], size=(h, w), mode="area")[0].permute(1, 2, 0)
    d = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))
    known = (d > 0).float()
    cols, wx = _taps(big_w, w, sigma_space, wrap)
    rows, wy = _taps(big_h, h, sigma_space, False)
    out = torch.zeros(big_h, big_w)
    for start in range(0, big_h, rows_per_chunk):
        r = rows[start : start + rows_per_chunk]  # [R,4]
        # spatial weight and what is known, per fine pixel and coarse neighbour: [R,W,4,4]
        space = wy[start : start + rows_per_chunk, None, :, None] * wx[None, :, None, :]
        grid_r, grid_c = r[:, None, :, None], cols[None, :, None, :]
        k = known[grid_r, grid_c] * space
        colour = coarse[grid_r, grid_c]  # [R,W,4,4,3]
        here = fine[start : start + rows_per_chunk, :, None, None, :]
        similar = torch.exp(-((colour - here) ** 2).sum(-1) / (2 * sigma_colour**2))
        weight = k * similar
        total = weight.sum((2, 3))
        # where no neighbour looks alike (a colour only the fine image has), the spatial weights alone
        weight = torch.where(total[..., None, None] > 1e-6, weight, k)
        value = (weight * d[grid_r, grid_c]).sum((2, 3)) / weight.sum((2, 3)).clamp(min=1e-12)
        seen = k.sum((2, 3)) >= 0.5 * space.sum((2, 3))
        out[start : start + rows_per_chunk] = torch.where(seen, value, torch.zeros(()))
    return out.numpy()
