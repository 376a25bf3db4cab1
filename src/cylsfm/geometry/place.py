"""Place recognition on the cylinder: a descriptor of a full panorama that does not change with the heading.

A camera that comes back to a place at another heading sees the same panorama rolled by a whole number of
columns (plus what the small change of position changes). A circular shift changes only the phase of the
discrete Fourier transform along the width, never its magnitude, so the magnitudes of the column-wise
transform are exactly invariant to the heading, also for a revisit in the opposite direction (a roll by
half the width). :func:`place_descriptor` takes, for a few horizontal bands of rows, the mean of each
column of the grey image and of its two gradient magnitudes, and keeps the magnitudes of their lowest
frequencies (the coarse layout of the street: facades, gaps, trees; the fine ones change with every metre);
the grey image is first brought to zero mean and unit variance (a change of exposure or contrast costs
nothing), and the concatenation, square-rooted and normalised to unit length, is the descriptor, compared by
:func:`place_distance` (one minus the cosine).

A mask fixed to the camera (a helmet, a mount) turns with the camera, not with the scene: the pixels under
it are left out of the band means (the mean of the pixels seen in each column), so the occluder adds
nothing; a panorama and its roll with the same mask give descriptors that differ only by what the mask
hides.
"""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError, ShapeError, check_shape

__all__ = ["place_descriptor", "place_distance"]

_LUMA = (0.299, 0.587, 0.114)


def place_descriptor(
    images: Tensor, mask: Tensor | None = None, bands: int = 8, frequencies: int = 16
) -> Tensor:
    """Heading-invariant descriptors of full panoramas (see the module docstring).

    Args:
        images: full 360-degree panoramas ``[B,3,H,W]`` in [0, 1] (``H`` at least ``bands``).
        mask: ``[B,1,H,W]`` or ``[1,1,H,W]``, 1 where the scene is seen, 0 on an occluder fixed to the
            camera; ``None``: every pixel.
        bands: horizontal bands of rows, each described on its own.
        frequencies: the lowest frequencies kept per band and channel (at most ``W // 2 + 1``).

    Returns:
        ``[B, 3 * bands * frequencies]`` float32, unit length.

    >>> x = torch.rand(2, 3, 16, 64)
    >>> d = place_descriptor(x, bands=4, frequencies=8)
    >>> bool(torch.allclose(d, place_descriptor(torch.roll(x, 17, dims=-1), bands=4, frequencies=8), atol=1e-5))
    True
    """
    check_shape(images, "B,3,H,W", "images")
    h, w = images.shape[-2:]
    if bands < 1 or frequencies < 1 or h < bands or frequencies > w // 2 + 1:
        raise InputError(
            f"place_descriptor: {bands} bands and {frequencies} frequencies do not fit {w}x{h} images"
        )
    x = images.float()
    lum = torch.tensor(_LUMA, device=x.device).reshape(1, 3, 1, 1)
    g = (x * lum).sum(1, keepdim=True)  # [B,1,H,W]
    m = None
    if mask is not None:
        check_shape(mask, "N,1,H,W", "mask")
        if mask.shape[-2:] != (h, w) or mask.shape[0] not in (1, x.shape[0]):
            raise ShapeError(f"mask {tuple(mask.shape)} does not fit images {tuple(images.shape)}")
        m = (mask > 0.5).expand_as(g)
    # zero mean and unit variance over the pixels seen: exposure and contrast changes cost nothing
    weight = torch.ones_like(g) if m is None else m.float()
    n_seen = weight.sum((2, 3), keepdim=True).clamp(min=2)
    mean = (g * weight).sum((2, 3), keepdim=True) / n_seen
    std = ((((g - mean) ** 2) * weight).sum((2, 3), keepdim=True) / (n_seen - 1)).sqrt().clamp(min=1e-6)
    g = (g - mean) / std
    du = (g - torch.roll(g, 1, dims=-1)).abs()  # circular: a roll of the image rolls it too
    dv = F.pad((g[..., 1:, :] - g[..., :-1, :]).abs(), (0, 0, 0, 1))
    channels = torch.cat((g, du, dv), 1)  # [B,3,H,W]
    if m is None:
        seen = torch.ones_like(channels)
    else:
        below = F.pad(m[..., 1:, :], (0, 0, 0, 1), value=False)
        # a gradient counts where both of its pixels are seen
        seen = torch.cat((m, m & torch.roll(m, 1, dims=-1), m & below), 1).float()
    edges = torch.linspace(0, h, bands + 1).round().long().tolist()
    rows = []
    for a, b in itertools.pairwise(edges):
        n = seen[..., a:b, :].sum(-2)  # [B,3,W]
        rows.append((channels[..., a:b, :] * seen[..., a:b, :]).sum(-2) / n.clamp(min=1))
    profile = torch.stack(rows, 2)  # [B,3,bands,W]
    spectrum = torch.fft.rfft(profile.double(), dim=-1).abs()[..., :frequencies] / w
    out = spectrum.sqrt().flatten(1).float()
    return out / out.norm(dim=1, keepdim=True).clamp(min=1e-12)


def place_distance(a: Tensor, b: Tensor) -> Tensor:
    """One minus the cosine between descriptors ``[N,D]`` and ``[M,D]``: ``[N,M]`` in [0, 2] (0: the same
    place as far as the descriptors can tell)."""
    return 1 - a @ b.T
