"""Photometric detail without aliasing: periodic noise tiles with mip levels, box-filtered patterns.

Surfaces are textured at the world point a ray hits. Every lookup takes the pixel's footprint on the
surface (metres) and averages the texture over it, so distant detail fades to its mean instead of
aliasing: noise tiles through their mip levels (:class:`Mip`), stripes, windows and joints analytically
(:func:`band`, :func:`pulse`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["TILE", "Mip", "band", "hash01", "periodic_noise", "pulse", "smoothstep"]

#: The size (texels) of the noise tiles.
TILE = 256


def periodic_noise(rng: np.random.Generator, size: int, falloff: float) -> np.ndarray:
    """A periodic ``size x size`` noise tile in [0, 1] with a ``1/f^falloff`` spectrum (FFT-filtered)."""
    white = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    rad = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    rad[0, 0] = 1.0
    spec = np.fft.fft2(white) / rad**falloff
    spec[0, 0] = 0
    tile = np.real(np.fft.ifft2(spec))
    tile = (tile - tile.mean()) / (tile.std() + 1e-12)
    return np.clip(0.5 + 0.18 * tile, 0, 1).astype(np.float32)


class Mip:
    """A periodic texture tile with its box-filtered mip levels, for footprint-aware (trilinear) lookups.

    Args:
        tile: ``[N, N]`` with ``N`` a power of two (the texture repeats with this period).
    """

    def __init__(self, tile: np.ndarray) -> None:
        levels = [tile.astype(np.float32)]
        while levels[-1].shape[0] > 1:
            t = levels[-1]
            levels.append(0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2]))
        self.sizes = np.array([lv.shape[0] for lv in levels], np.int32)
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes**2)[:-1]]).astype(np.int64)
        self.atlas = np.concatenate([lv.ravel() for lv in levels])
        self.top = len(levels) - 1

    def _bilinear(self, level: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        n = self.sizes[level]
        mask = n - 1
        x = x / (1 << level).astype(np.float32) - np.float32(0.5)
        y = y / (1 << level).astype(np.float32) - np.float32(0.5)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        ix, iy = x0.astype(np.int64) & mask, y0.astype(np.int64) & mask
        ix1, iy1 = (ix + 1) & mask, (iy + 1) & mask
        base = self.offsets[level]
        a = self.atlas
        top = a[base + iy * n + ix] * (1 - fx) + a[base + iy * n + ix1] * fx
        bot = a[base + iy1 * n + ix] * (1 - fx) + a[base + iy1 * n + ix1] * fx
        return top * (1 - fy) + bot * fy

    def sample(self, u: np.ndarray, v: np.ndarray, scale: float, footprint: np.ndarray) -> np.ndarray:
        """Texture at surface coordinates ``(u, v)`` (metres) at ``scale`` texels per metre, averaged over
        a footprint of ``footprint`` metres (the level of detail is ``log2`` of its size in texels)."""
        x = u * np.float32(scale)
        y = v * np.float32(scale)
        lod = np.clip(np.log2(np.maximum(footprint * np.float32(scale), np.float32(1))), 0, self.top - 1e-3)
        l0 = np.floor(lod).astype(np.int64)
        frac = (lod - l0).astype(np.float32)
        return self._bilinear(l0, x, y) * (1 - frac) + self._bilinear(l0 + 1, x, y) * frac


def band(x: np.ndarray, lo: float | np.ndarray, hi: float | np.ndarray, fw: np.ndarray) -> np.ndarray:
    """Fraction of the window ``[x - fw/2, x + fw/2]`` inside ``[lo, hi]``: a box-filtered indicator."""
    h = np.float32(0.5) * fw
    return (np.clip(x + h, lo, hi) - np.clip(x - h, lo, hi)) / np.maximum(fw, np.float32(1e-6))


def pulse(x: np.ndarray, period: float | np.ndarray, lo: float, hi: float, fw: np.ndarray) -> np.ndarray:
    """Box-filtered periodic pulse train: the fraction of ``[x - fw/2, x + fw/2]`` where
    ``frac(x / period)`` lies in ``[lo, hi]`` (analytic, so it never aliases)."""

    def integral(y):
        q = y / period
        n = np.floor(q)
        return (n * (hi - lo) + np.clip(q - n, lo, hi) - lo) * period

    fw = np.maximum(fw, np.float32(1e-6))
    h = np.float32(0.5) * fw
    return np.clip((integral(x + h) - integral(x - h)) / fw, 0, 1)


def hash01(*ints: np.ndarray) -> np.ndarray:
    """Deterministic hash of integer arrays to [0, 1) (integer arithmetic only)."""
    h = np.uint64(0x9E3779B97F4A7C15)
    acc = np.zeros(np.broadcast(*ints).shape, np.uint64)
    for v in ints:
        acc = acc ^ (
            np.asarray(v).astype(np.int64).astype(np.uint64)
            + h
            + (acc << np.uint64(6))
            + (acc >> np.uint64(2))
        )
        acc = acc * np.uint64(0xBF58476D1CE4E5B9)
        acc = acc ^ (acc >> np.uint64(31))
    return (acc >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at ``e0`` to 1 at ``e1``."""
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)
