"""Depth measures as small functions and accumulators: the errors of Eigen et al., SfMLearner's median
scaling, the seam and centre columns of full panoramas, and the per-row prior baseline.

Depths are in metres (ground truth) or any positive units (predictions, median-scaled). Maps are ``[H,W]``
(``[1,H,W]`` and ``[1,1,H,W]`` are accepted); NumPy arrays and tensors alike.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch

from ..errors import InputError
from ..geometry import resize_image

__all__ = [
    "DEPTH_METRICS",
    "DepthAccumulator",
    "RowPrior",
    "as_depth_map",
    "check_depth_range",
    "check_seam_fraction",
    "depth_errors",
    "evaluate_depth_maps",
    "resize_depth",
]

#: The error measures, in table order. Lower is better for the first five, higher for ``a1..a3``.
DEPTH_METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


# --------------------------------------------------------------------------------------- measures
def _as_array(x: Any) -> np.ndarray:
    """Tensor or array-like -> float64 numpy array (leading singleton dimensions of maps are kept)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def as_depth_map(x: Any, what: str) -> np.ndarray:
    """``[H,W]``, ``[1,H,W]`` or ``[1,1,H,W]`` (array or tensor) -> float64 ``[H,W]``.

    Raises:
        InputError: another shape (the message names ``what``).
    """
    arr = _as_array(x)
    while arr.ndim > 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2:
        raise InputError(f"{what} must be a [H,W] map, got shape {arr.shape}")
    return arr


def check_depth_range(min_depth: float, max_depth: float) -> None:
    """Raise :class:`InputError` unless ``0 < min_depth < max_depth`` (metres)."""
    if not 0 < min_depth < max_depth:
        raise InputError(f"need 0 < min_depth < max_depth, got {min_depth} and {max_depth}")


def check_seam_fraction(seam_fraction: float) -> None:
    """Raise :class:`InputError` unless ``0 <= seam_fraction <= 1`` (0 to 180 degrees at each side)."""
    if not 0 <= seam_fraction <= 1:
        raise InputError(
            f"seam_fraction must be in [0, 1] (0 to 180 degrees at each side of the seam), got {seam_fraction}"
        )


def depth_errors(gt: Any, pred: Any) -> dict[str, float]:
    """The depth error measures of Eigen et al. (NIPS 2014) over matching pixels.

    Args:
        gt: ground-truth depths ``[N]`` (any shape; flattened), all > 0.
        pred: predicted depths, same shape and units, all > 0.

    Returns:
        ``abs_rel = mean(|gt - pred| / gt)``, ``sq_rel = mean((gt - pred)^2 / gt)``,
        ``rmse = sqrt(mean((gt - pred)^2))``, ``rmse_log = sqrt(mean((ln gt - ln pred)^2))`` and the
        accuracies ``a_k = mean(max(gt/pred, pred/gt) < 1.25^k)`` for ``k = 1, 2, 3`` (fractions in [0, 1]).
        Lengths are in the units of the inputs (``rmse``), ``sq_rel`` too (it divides a squared length by
        a length).
    """
    g = _as_array(gt).reshape(-1)
    p = _as_array(pred).reshape(-1)
    if g.shape != p.shape:
        raise InputError(f"gt and pred must have the same number of values, got {g.size} and {p.size}")
    if g.size == 0:
        raise InputError("no pixels to evaluate")
    if not (np.all(g > 0) and np.all(p > 0)):
        raise InputError("depths must be positive (mask out unknown ground truth, clamp predictions)")
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(p))):
        raise InputError("depths must be finite")
    ratio = np.maximum(g / p, p / g)
    diff = g - p
    log_diff = np.log(g) - np.log(p)
    return {
        "abs_rel": float(np.mean(np.abs(diff) / g)),
        "sq_rel": float(np.mean(diff * diff / g)),
        "rmse": float(np.sqrt(np.mean(diff * diff))),
        "rmse_log": float(np.sqrt(np.mean(log_diff * log_diff))),
        "a1": float(np.mean(ratio < 1.25)),
        "a2": float(np.mean(ratio < 1.25**2)),
        "a3": float(np.mean(ratio < 1.25**3)),
    }


def resize_depth(pred: Any, size: tuple[int, int], wrap: bool = False) -> np.ndarray:
    """Bilinear resize (``align_corners=False``, pixel centres as in ``docs/conventions.md``) of a depth map.

    Args:
        pred: ``[h,w]`` depth map.
        size: ``(H, W)`` wanted.
        wrap: the columns are a full 360-degree panorama: blend across the seam (only when ``W`` is an
            integer multiple of ``w``; otherwise plain bilinear).

    Returns:
        float64 ``[H,W]``.
    """
    arr = as_depth_map(pred, "prediction")
    if arr.shape == tuple(size):
        return arr
    x = torch.from_numpy(np.ascontiguousarray(arr))[None, None]
    wrap = wrap and size[1] % arr.shape[1] == 0
    return resize_image(x, (int(size[0]), int(size[1])), wrap=wrap)[0, 0].numpy()


class DepthAccumulator:
    """Scores depth maps one image at a time and averages the measures over images.

    Args:
        min_depth, max_depth: valid ground truth lies strictly between them (metres); scaled predictions
            are clamped to ``[min_depth, max_depth]``.
        median_scaling: multiply each prediction by ``median(gt) / median(pred)`` over its valid pixels.
        seam_fraction: also score the columns next to the seam of full panoramas (images added with
            ``seam=True``): this share of the width, half of it at each side (the columns that a network
            without wrap-around sees next to its zero padding), and as a control the same number of
            columns around the image centre, opposite the seam (the same kind of view, far from any image
            border). The image's scale is the one of the whole image. ``0`` turns it off.
    """

    def __init__(
        self,
        min_depth: float = 1e-3,
        max_depth: float = 80.0,
        median_scaling: bool = True,
        seam_fraction: float = 0.0,
    ) -> None:
        check_depth_range(min_depth, max_depth)
        check_seam_fraction(seam_fraction)
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        self.median_scaling = median_scaling
        self.seam_fraction = float(seam_fraction)
        self.rows: list[dict[str, float]] = []
        self.seam_rows: list[dict[str, float]] = []
        self.centre_rows: list[dict[str, float]] = []
        self.scales: list[float] = []
        self.skipped = 0

    def valid(self, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Boolean ``[H,W]``: pixels with usable ground truth (and inside ``mask`` when given)."""
        ok = (gt > self.min_depth) & (gt < self.max_depth)
        if mask is not None:
            ok &= np.asarray(mask) > 0.5
        return ok

    def seam_columns(self, width: int) -> int:
        """Columns scored at each side of the seam of a panorama ``width`` wide (0: seam scoring off)."""
        if self.seam_fraction <= 0:
            return 0
        return max(1, round(width * self.seam_fraction / 2))

    def add(self, gt: Any, pred: Any, mask: Any | None = None, seam: bool = False) -> float | None:
        """Score one image.

        Args:
            gt: ground truth ``[H,W]`` (metres, 0 = unknown).
            pred: prediction ``[H,W]`` (same size; any positive units).
            mask: optional ``[H,W]``, pixels > 0.5 are used.
            seam: the image is a full 360-degree panorama: also score its seam and centre columns (see
                ``seam_fraction``).

        Returns:
            The image's scale factor, or ``None`` when it has no valid pixel (it is then skipped and
            counted in :attr:`skipped`).

        Raises:
            InputError: sizes differ, or the prediction's median over the valid pixels is not positive.
        """
        g = as_depth_map(gt, "ground truth")
        p = as_depth_map(pred, "prediction")
        if g.shape != p.shape:
            raise InputError(f"ground truth is {g.shape} but the prediction is {p.shape}")
        ok = self.valid(g, None if mask is None else as_depth_map(mask, "mask"))
        if not ok.any():
            self.skipped += 1
            return None
        gv, pv = g[ok], p[ok]
        if not np.all(np.isfinite(pv)):
            raise InputError("the prediction has non-finite values")
        scale = 1.0
        if self.median_scaling:
            med = float(np.median(pv))
            if not med > 0:
                raise InputError(f"the prediction's median over valid pixels is {med}, not positive")
            scale = float(np.median(gv)) / med
        pv = np.clip(pv * scale, self.min_depth, self.max_depth)
        self.rows.append(depth_errors(gv, pv))
        self.scales.append(scale)
        if seam and self.seam_columns(g.shape[1]):
            self._add_bands(np.nonzero(ok)[1], g.shape[1], gv, pv)
        return scale

    def _add_bands(self, cols: np.ndarray, width: int, gv: np.ndarray, pv: np.ndarray) -> None:
        """Score the seam and the centre columns of one image: ``gv``, ``pv`` ``[N]`` are its valid ground
        truth and scaled prediction, ``cols [N]`` their columns (row-major order, as ``np.nonzero``)."""
        k, w = self.seam_columns(width), width
        for rows, sel in (
            (self.seam_rows, (cols < k) | (cols >= w - k)),
            (self.centre_rows, (cols >= w // 2 - k) & (cols < w // 2 + k)),
        ):
            if sel.any():
                rows.append(depth_errors(gv[sel], pv[sel]))

    def result(self) -> dict[str, float | int]:
        """The measures of :data:`DEPTH_METRICS` averaged over images, ``n_images``, ``scale_mean`` and
        ``scale_std`` (population standard deviation) of the per-image scales. NaN when no image counted.
        ``"seam"`` and ``"centre"``: the same measures over the seam columns only and over the centre
        columns only (averaged over the images that have some, with their count as ``n_images``), or
        ``None`` when none was scored."""
        n = len(self.rows)
        out: dict[str, Any] = {
            k: (float(np.mean([r[k] for r in self.rows])) if n else math.nan) for k in DEPTH_METRICS
        }
        out["n_images"] = n
        out["scale_mean"] = float(np.mean(self.scales)) if n else math.nan
        out["scale_std"] = float(np.std(self.scales)) if n else math.nan
        for name, rows in (("seam", self.seam_rows), ("centre", self.centre_rows)):
            part: dict[str, Any] | None = None
            if rows:
                part = {k: float(np.mean([r[k] for r in rows])) for k in DEPTH_METRICS}
                part["n_images"] = len(rows)
            out[name] = part
        return out


def evaluate_depth_maps(
    pairs: Iterable[tuple[Any, Any]],
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    median_scaling: bool = True,
) -> dict[str, float | int]:
    """Score ``(gt [H,W], pred [H,W])`` pairs (numpy arrays or tensors) with the protocol of
    :mod:`cylsfm.evaluate.depth`.

    A prediction of another size is resized to the ground truth's bilinearly. Ground truth is in metres
    (0 = unknown); images without a valid pixel are skipped.

    Returns:
        ``{abs_rel, sq_rel, rmse, rmse_log, a1, a2, a3}`` averaged over images, plus ``n_images``,
        ``scale_mean`` and ``scale_std`` (the per-image median-scaling factors; 1 without scaling).
    """
    acc = DepthAccumulator(min_depth, max_depth, median_scaling)
    for gt, pred in pairs:
        g = as_depth_map(gt, "ground truth")
        acc.add(g, resize_depth(pred, g.shape))
    return acc.result()


# --------------------------------------------------------------------------------------- row prior
class RowPrior:
    """Median ground-truth depth of every image row over many frames (the ``per_row`` baseline).

    Medians are taken from per-row histograms of ``ln(depth)`` with ``bins`` bins over
    ``(min_depth, max_depth)`` (the middle order statistics are placed inside their bins by rank), so memory
    does not grow with the number of frames; with the default 8192 bins over ``(1e-3, 80)`` the median is
    within 0.14 % of the exact one. All frames must have the height of the first one added (other heights are resampled
    to it by nearest row).

    Args:
        min_depth, max_depth: only depths strictly between them count (metres).
        bins: histogram bins per row.
    """

    def __init__(self, min_depth: float = 1e-3, max_depth: float = 80.0, bins: int = 8192) -> None:
        check_depth_range(min_depth, max_depth)
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        self.bins = int(bins)
        self._lo = math.log(self.min_depth)
        self._width = (math.log(self.max_depth) - self._lo) / self.bins
        self.hist: np.ndarray | None = None  # int64 [H, bins]
        self.n_images = 0

    @property
    def height(self) -> int | None:
        """Rows of the prior (the height of the first frame added), or ``None`` before any frame."""
        return None if self.hist is None else int(self.hist.shape[0])

    def add(self, depth: Any, mask: Any | None = None) -> None:
        """Add one ground-truth map ``[H,W]`` (metres, 0 = unknown); ``mask [H,W]`` > 0.5 keeps pixels."""
        d = as_depth_map(depth, "depth")
        ok = (d > self.min_depth) & (d < self.max_depth)
        if mask is not None:
            ok &= as_depth_map(mask, "mask") > 0.5
        if self.hist is None:
            self.hist = np.zeros((d.shape[0], self.bins), dtype=np.int64)
        h = self.hist.shape[0]
        if d.shape[0] != h:
            rows = np.minimum(((np.arange(h) + 0.5) * (d.shape[0] / h)).astype(np.int64), d.shape[0] - 1)
            d, ok = d[rows], ok[rows]
        r, c = np.nonzero(ok)
        b = np.clip(((np.log(d[r, c]) - self._lo) / self._width).astype(np.int64), 0, self.bins - 1)
        self.hist += np.bincount(r * self.bins + b, minlength=h * self.bins).reshape(h, self.bins)
        self.n_images += 1

    def medians(self) -> np.ndarray | None:
        """float64 ``[H]``: each row's median depth; rows without data take the value of the nearest rows
        with data (linear interpolation between them). ``None`` when no row has data."""
        if self.hist is None:
            return None
        counts = self.hist.sum(1)
        has = counts > 0
        if not has.any():
            return None
        cum = np.cumsum(self.hist, axis=1)
        out = np.full(self.hist.shape[0], np.nan)
        for r in np.nonzero(has)[0]:
            n = int(counts[r])
            vals = []
            for rank in {(n - 1) // 2, n // 2}:  # the middle one or two order statistics
                k = int(np.searchsorted(cum[r], rank, side="right"))  # the bin holding that rank
                before = cum[r, k - 1] if k else 0
                frac = (rank - before + 0.5) / self.hist[r, k]
                vals.append(math.exp(self._lo + (k + frac) * self._width))
            out[r] = float(np.mean(vals))
        rows = np.arange(len(out))
        return np.interp(rows, rows[has], out[has])

    def depth_map(self, height: int, width: int) -> np.ndarray | None:
        """The prior as a depth map ``[height, width]``: the row medians resampled to ``height`` rows
        (linear interpolation at pixel centres, ``v' = (v + 0.5) H / height - 0.5``), equal along rows."""
        med = self.medians()
        if med is None:
            return None
        h = len(med)
        src = np.clip((np.arange(height) + 0.5) * (h / height) - 0.5, 0, h - 1)
        col = np.interp(src, np.arange(h), med)
        return np.repeat(col[:, None], width, axis=1)
