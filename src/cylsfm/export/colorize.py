"""Colour pictures of depth maps, and stacking pictures for previews.

Depth is shown as inverse depth (disparity), which spreads the near range where a depth network's detail
is, and is normalised with robust percentiles so that a few far (sky) or very near pixels do not wash out
the rest: near is bright, far is dark, unknown depth (0, negative or non-finite) is black.
"""

from __future__ import annotations

import math
import os
import sys
from functools import lru_cache

import numpy as np

from ..errors import CylsfmError

__all__ = ["colorize_depth", "depth_limits", "depth_panels", "depth_picture", "side_by_side"]

#: Percentiles of the valid inverse depth mapped to the ends of the colour map when no limit is given.
PERCENTILES = (5.0, 95.0)


@lru_cache(maxsize=8)
def _lut(cmap: str) -> np.ndarray:
    """The colour map ``cmap`` as a ``uint8 [256,3]`` lookup table (matplotlib, imported here)."""
    if "matplotlib" not in sys.modules:
        # only colour maps are used, never a window: keep matplotlib off any interactive backend
        os.environ.setdefault("MPLBACKEND", "Agg")
    try:
        import matplotlib
    except ImportError:
        raise CylsfmError("colourising depth needs matplotlib (pip install matplotlib)") from None
    try:
        cm = matplotlib.colormaps[cmap]
    except KeyError:
        raise CylsfmError(f"unknown matplotlib colour map {cmap!r}") from None
    rgba = cm(np.linspace(0.0, 1.0, 256))
    return np.round(np.asarray(rgba)[:, :3] * 255).astype(np.uint8)


def colorize_depth(
    depth: np.ndarray, vmin: float | None = None, vmax: float | None = None, cmap: str = "magma"
) -> np.ndarray:
    """Colour a depth map by its inverse depth.

    Args:
        depth: ``[H,W]`` depth (any unit; a network's depth or metres); values that are 0, negative or
            not finite are unknown.
        vmin: depth (same unit) shown with the brightest colour; nearer pixels are clipped to it. Default:
            the depth at the 95th percentile of the valid inverse depth.
        vmax: depth shown with the darkest colour; farther pixels are clipped to it. Default: the depth at
            the 5th percentile of the valid inverse depth. Fix both to compare frames (e.g. of a video).
        cmap: a matplotlib colour map name, read from its dark (far) to its bright (near) end for the
            usual sequential maps (magma, inferno, viridis ...).

    Returns:
        ``uint8 [H,W,3]`` RGB; unknown pixels are black ``(0, 0, 0)``. When every valid pixel has the same
        inverse depth, they all take the colour map's middle colour.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be [H,W], got shape {d.shape}")
    for name, lim in (("vmin", vmin), ("vmax", vmax)):
        if lim is not None and not (math.isfinite(lim) and lim > 0):
            raise ValueError(f"{name} must be a positive depth, got {lim}")
    d = d.astype(np.float64, copy=False)
    valid = np.isfinite(d) & (d > 0)
    out = np.zeros((*d.shape, 3), dtype=np.uint8)
    if not valid.any():
        return out
    vals = 1.0 / d[valid]  # inverse depth of the valid pixels
    lo = 1.0 / vmax if vmax is not None else None
    hi = 1.0 / vmin if vmin is not None else None
    if lo is None or hi is None:
        p_lo, p_hi = np.percentile(vals, PERCENTILES)
        lo = p_lo if lo is None else lo
        hi = p_hi if hi is None else hi
    span = hi - lo
    if not span > 0:
        t = np.full(vals.shape, 0.5)
    else:
        t = np.clip((vals - lo) / span, 0.0, 1.0)
    idx = np.round(t * 255).astype(np.intp)
    out[valid] = _lut(cmap)[idx]
    return out


def side_by_side(images: list[np.ndarray], separator: int = 2, colour: int = 255) -> np.ndarray:
    """Stack ``uint8`` pictures vertically (panoramas are wide) with a thin separating band.

    Args:
        images: ``uint8 [H_i,W,3]`` (or grey ``[H_i,W]``) pictures of one width ``W``.
        separator: height in pixels of the band between two pictures.
        colour: grey value of the band.

    Returns:
        ``uint8 [sum(H_i) + separator * (n - 1), W, 3]``.
    """
    if not images:
        raise ValueError("side_by_side needs at least one image")
    rows = []
    width = None
    for i, im in enumerate(images):
        a = np.asarray(im)
        if a.dtype != np.uint8:
            raise ValueError(f"image {i} must be uint8, got {a.dtype}")
        if a.ndim == 2:
            a = np.repeat(a[:, :, None], 3, axis=2)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"image {i} must be [H,W,3] or [H,W], got shape {a.shape}")
        if width is None:
            width = a.shape[1]
        elif a.shape[1] != width:
            raise ValueError(f"images must share one width, got {width} and {a.shape[1]} (image {i})")
        if rows and separator > 0:
            rows.append(np.full((separator, width, 3), colour, dtype=np.uint8))
        rows.append(a)
    return np.ascontiguousarray(np.concatenate(rows, axis=0))


def depth_limits(depth: np.ndarray) -> tuple[float, float] | None:
    """The depths ``(vmin, vmax)`` :func:`colorize_depth` maps to its brightest and darkest colours by
    default (``None`` without a valid pixel)."""
    d = np.asarray(depth, dtype=np.float64)
    vals = 1.0 / d[np.isfinite(d) & (d > 0)]
    if not len(vals):
        return None
    p_lo, p_hi = np.percentile(vals, PERCENTILES)
    return 1.0 / p_hi, 1.0 / p_lo


def _font(scale: int):
    """Pillow's default font at ``11 * scale`` pixels (a fixed bitmap font on Pillow < 10.1)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=11 * scale)
    except TypeError:
        return ImageFont.load_default()


def _caption(width: int, text: str, scale: int) -> np.ndarray:
    """A black strip of ``width`` pixels with ``text`` in light grey: a panel's title."""
    from PIL import Image, ImageDraw

    im = Image.new("RGB", (width, 16 * scale))
    ImageDraw.Draw(im).text((4, 2 * scale), text, fill=(220, 220, 220), font=_font(scale))
    return np.asarray(im)


def _ticks(vmin: float, vmax: float, n: int = 5) -> list[float]:
    """About ``n`` round depths between ``vmin`` and ``vmax``, evenly spread in inverse depth."""
    out = []
    for t in np.linspace(0.0, 1.0, n):
        inv = 1 / vmax + t * (1 / vmin - 1 / vmax)
        d = 1 / inv
        digits = 2 - math.floor(math.log10(d))
        value = round(d, max(digits - 1, -6))
        if value > 0 and (not out or value != out[-1]):
            out.append(value)
    return out


def _colour_bar(width: int, vmin: float, vmax: float, unit: str, cmap: str, scale: int) -> np.ndarray:
    """A strip: the colour map from far (left) to near (right) with depth labels below."""
    from PIL import Image, ImageDraw

    title_h, bar_h, text_h = 16 * scale, 12 * scale, 16 * scale
    ramp = np.linspace(0, 255, width).round().astype(np.intp)
    strip = np.zeros((title_h + bar_h + text_h, width, 3), dtype=np.uint8)
    strip[title_h : title_h + bar_h] = _lut(cmap)[ramp][None]
    im = Image.fromarray(strip)
    draw = ImageDraw.Draw(im)
    font = _font(scale)
    lo, hi = 1 / vmax, 1 / vmin
    for d in _ticks(vmin, vmax):
        x = round((1 / d - lo) / (hi - lo) * (width - 1)) if hi > lo else width // 2
        draw.line([(x, title_h), (x, title_h + bar_h + 2 * scale)], fill=(255, 255, 255), width=1)
        xy = (min(max(x + 2, 0), width - 40 * scale), title_h + bar_h + 2 * scale)
        draw.text(xy, f"{d:g}", fill=(255, 255, 255), font=font)
    draw.text((4, 2 * scale), f"depth ({unit}): far is dark, near is bright", fill=(220, 220, 220), font=font)
    return np.asarray(im)


def depth_picture(
    image: np.ndarray,
    depth: np.ndarray,
    unit: str = "network units",
    min_width: int = 1024,
    cmap: str = "magma",
    limits: tuple[float, float] | None = None,
) -> np.ndarray:
    """A picture a person can read: the input above its coloured depth, both enlarged by a whole factor to
    at least ``min_width`` pixels (the depth by repeating pixels), and a colour scale labelled in ``unit``.

    ``image`` ``uint8 [H,W,3]`` and ``depth [H,W]`` are of one camera; ``limits``: the depths of the
    brightest and darkest colours (default: this depth's, :func:`depth_limits`; fix them to compare the
    frames of a video). Returns ``uint8`` RGB.
    """
    return depth_panels(image, [depth], unit, min_width=min_width, cmap=cmap, limits=limits)


def depth_panels(
    image: np.ndarray,
    depths: list[np.ndarray],
    unit: str = "network units",
    labels: list[str] | None = None,
    min_width: int = 1024,
    cmap: str = "magma",
    limits: tuple[float, float] | None = None,
) -> np.ndarray:
    """The input above one or more depth maps of it (e.g. a prediction and the ground truth), all coloured
    with one colour scale, enlarged by a whole factor to at least ``min_width`` pixels (the depth by
    repeating pixels, the input bicubically), and under them the colour scale labelled in ``unit``.

    ``image`` ``uint8 [H',W',3]`` (resized to the depth's size) and every ``depths[i]`` ``[H,W]`` are of one
    camera. ``labels``: one title for the input and one for each depth map, each drawn in a strip above its
    panel (``None``: no titles). ``limits``: the depths of the brightest and darkest colours (default: the first depth map's,
    :func:`depth_limits`). Returns ``uint8`` RGB.
    """
    from PIL import Image

    if not depths:
        raise ValueError("depth_panels needs at least one depth map")
    h, w = depths[0].shape
    if any(d.shape != (h, w) for d in depths):
        raise ValueError("the depth maps must have one size")
    if labels is not None and len(labels) != 1 + len(depths):
        raise ValueError(
            f"labels: one for the image and one per depth map, {1 + len(depths)}, got {len(labels)}"
        )
    k = max(1, math.ceil(min_width / w))
    scale = max(1, round(w * k / 1024))
    limits = limits or depth_limits(depths[0]) or (1.0, 2.0)
    big_image = np.asarray(
        Image.fromarray(np.ascontiguousarray(image)).resize((w * k, h * k), Image.Resampling.BICUBIC)
    )
    panels = [big_image]
    for depth in depths:
        colour = colorize_depth(depth, *limits, cmap=cmap)
        panels.append(np.repeat(np.repeat(colour, k, 0), k, 1))
    if labels is not None:
        panels = [
            part
            for label, panel in zip(labels, panels, strict=True)
            for part in (_caption(w * k, label, scale), panel)
        ]
    bar = _colour_bar(w * k, limits[0], limits[1], unit, cmap, scale)
    return side_by_side([*panels, bar], separator=2, colour=0)
