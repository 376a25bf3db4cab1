"""Depth evaluation: the error measures of Eigen et al. with SfMLearner's median scaling, and baselines.

Protocol (SfMLearner / monodepth2), per image:

1. valid pixels: ``min_depth < gt < max_depth`` (and, where the sequence has ``mask.png``, mask pixels);
2. the prediction is multiplied by ``median(gt) / median(pred)`` over the valid pixels (median scaling:
   monocular depth has an unknown scale); that factor is the image's *scale*;
3. the scaled prediction is clamped to ``[min_depth, max_depth]``;
4. :func:`depth_errors` on the valid pixels.

The measures are averaged over images (each image weighs the same). The mean and standard deviation of the
per-image scales tell whether the network's scale is consistent from frame to frame (a small
``scale_std / scale_mean`` means a single global scale would do almost as well).

Baselines, scored on the same frames and pixels with the same protocol:

- ``"constant"``: one constant everywhere. After median scaling it predicts ``median(gt)`` at every pixel.
- ``"per_row"``: every image row predicts that row's median ground-truth depth over the frames of the
  *training* split (:class:`RowPrior`). On a level panorama the ground is below the horizon and far things
  sit near it, so a row prior is a strong baseline: a model must beat it to have learned more than the
  layout of a street.

Depths are in metres (ground truth) or network units (predictions, scaled away). Images are ``[H,W]``.
"""

from __future__ import annotations

import math
import os
from collections import deque
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..data.format import DatasetError, SequenceInfo, load_depth, load_image, load_mask, scan_dataset
from ..data.splits import SPLIT_PARTS, read_split, split_path
from ..geometry import resize_image

__all__ = [
    "DEPTH_METRICS",
    "DepthAccumulator",
    "RowPrior",
    "depth_errors",
    "depth_json",
    "evaluate_depth",
    "evaluate_depth_maps",
    "format_depth_table",
    "load_prediction",
    "prediction_path",
    "resize_depth",
    "split_entries",
]

#: The error measures, in table order. Lower is better for the first five, higher for ``a1..a3``.
DEPTH_METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")

PathLike = str | os.PathLike[str]


# --------------------------------------------------------------------------------------- measures
def _as_array(x: Any) -> np.ndarray:
    """Tensor or array-like -> float64 numpy array (leading singleton dimensions of maps are kept)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def _as_map(x: Any, what: str) -> np.ndarray:
    """``[H,W]``, ``[1,H,W]`` or ``[1,1,H,W]`` -> float64 ``[H,W]``."""
    arr = _as_array(x)
    while arr.ndim > 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2:
        raise ValueError(f"{what} must be a [H,W] map, got shape {arr.shape}")
    return arr


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
        raise ValueError(f"gt and pred must have the same number of values, got {g.size} and {p.size}")
    if g.size == 0:
        raise ValueError("no pixels to evaluate")
    if not (np.all(g > 0) and np.all(p > 0)):
        raise ValueError("depths must be positive (mask out unknown ground truth, clamp predictions)")
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(p))):
        raise ValueError("depths must be finite")
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
    arr = _as_map(pred, "prediction")
    if arr.shape == tuple(size):
        return arr
    x = torch.from_numpy(np.ascontiguousarray(arr))[None, None]
    if wrap and size[1] % arr.shape[1] == 0:
        out = resize_image(x, (int(size[0]), int(size[1])), wrap=True)
    else:
        out = F.interpolate(x, size=(int(size[0]), int(size[1])), mode="bilinear", align_corners=False)
    return out[0, 0].numpy()


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
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth} and {max_depth}")
        if not 0 <= seam_fraction <= 1:
            raise ValueError(f"seam_fraction must be in [0, 1], got {seam_fraction}")
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
            ValueError: sizes differ, or the prediction's median over the valid pixels is not positive.
        """
        g = _as_map(gt, "ground truth")
        p = _as_map(pred, "prediction")
        if g.shape != p.shape:
            raise ValueError(f"ground truth is {g.shape} but the prediction is {p.shape}")
        ok = self.valid(g, None if mask is None else _as_map(mask, "mask"))
        if not ok.any():
            self.skipped += 1
            return None
        gv, pv = g[ok], p[ok]
        if not np.all(np.isfinite(pv)):
            raise ValueError("the prediction has non-finite values")
        scale = 1.0
        if self.median_scaling:
            med = float(np.median(pv))
            if not med > 0:
                raise ValueError(f"the prediction's median over valid pixels is {med}, not positive")
            scale = float(np.median(gv)) / med
        pv = np.clip(pv * scale, self.min_depth, self.max_depth)
        self.rows.append(depth_errors(gv, pv))
        self.scales.append(scale)
        k = self.seam_columns(g.shape[1]) if seam else 0
        if k:
            w = g.shape[1]
            cols = np.nonzero(ok)[1]  # the columns of gv / pv, in the same (row-major) order
            for rows, sel in (
                (self.seam_rows, (cols < k) | (cols >= w - k)),
                (self.centre_rows, (cols >= w // 2 - k) & (cols < w // 2 + k)),
            ):
                if sel.any():
                    rows.append(depth_errors(gv[sel], pv[sel]))
        return scale

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
    """Score ``(gt [H,W], pred [H,W])`` pairs (numpy arrays or tensors) with the protocol of the module.

    A prediction of another size is resized to the ground truth's bilinearly. Ground truth is in metres
    (0 = unknown); images without a valid pixel are skipped.

    Returns:
        ``{abs_rel, sq_rel, rmse, rmse_log, a1, a2, a3}`` averaged over images, plus ``n_images``,
        ``scale_mean`` and ``scale_std`` (the per-image median-scaling factors; 1 without scaling).
    """
    acc = DepthAccumulator(min_depth, max_depth, median_scaling)
    for gt, pred in pairs:
        g = _as_map(gt, "ground truth")
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
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth} and {max_depth}")
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
        d = _as_map(depth, "depth")
        ok = (d > self.min_depth) & (d < self.max_depth)
        if mask is not None:
            ok &= _as_map(mask, "mask") > 0.5
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


# --------------------------------------------------------------------------------------- dataset I/O
def split_entries(
    root: PathLike, split: str | PathLike | None, split_name: str, sequences: Sequence[SequenceInfo]
) -> list[tuple[str, str]] | None:
    """The ``(sequence, frame)`` entries of a split, or ``None`` for ``split=None`` (every frame).

    ``split`` is ``"train"``, ``"val"`` or ``"test"`` (``ROOT/splits/<split_name>/<split>.txt``) or the
    path of a split file.
    """
    if split is None:
        return None
    if isinstance(split, str) and split in SPLIT_PARTS:
        path = split_path(root, split, split_name)
        if not path.exists():
            raise DatasetError(f"{path}: split file not found (write it with cylsfm.data.make_splits)")
    else:
        path = Path(split)
    return read_split(path, root, sequences)


def _frames_of(
    sequences: Sequence[SequenceInfo], entries: list[tuple[str, str]] | None
) -> list[tuple[SequenceInfo, int]]:
    """``(sequence, frame index)`` of split entries (every frame for ``None``), in dataset order, unique."""
    if entries is None:
        return [(s, i) for s in sequences for i in range(len(s)) if i not in s.bad]
    wanted = {(a, b) for a, b in entries}
    return [(s, i) for s in sequences for i, stem in enumerate(s.stems) if (s.name, stem) in wanted]


def prediction_path(pred_root: PathLike, sequence: SequenceInfo, single: bool) -> tuple[Path, ...]:
    """Where the predictions of a sequence may be, in the order they are looked for: ``PRED/SEQ/`` then
    ``PRED/SEQ/depth/``, and for a single-sequence dataset also ``PRED/`` itself (file ``FRAME.npy``)."""
    root = Path(pred_root)
    dirs = [root / sequence.name, root / sequence.name / "depth"]
    if single:
        dirs.append(root)
    return tuple(dirs)


def load_prediction(dirs: Sequence[Path], stem: str) -> np.ndarray:
    """Load ``STEM.npy`` from the first of ``dirs`` that has it: float64 ``[h,w]`` (``[1,h,w]`` and
    ``[1,1,h,w]`` are accepted). Missing, unreadable, non-numeric or non-finite -> :class:`DatasetError`."""
    for d in dirs:
        path = d / f"{stem}.npy"
        if path.is_file():
            break
    else:
        raise DatasetError(f"{dirs[0] / f'{stem}.npy'}: prediction not found")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise DatasetError(f"{path}: cannot read prediction ({exc})") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise DatasetError(f"{path}: a prediction must be one numeric .npy array")
    try:
        out = _as_map(arr, "prediction")
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from None
    if not np.all(np.isfinite(out)):
        raise DatasetError(f"{path}: prediction has non-finite values (NaN or inf)")
    return out


def _roll_columns(x: np.ndarray, k: int) -> np.ndarray:
    """``[H,W,...]`` rolled by ``k`` columns (a yaw turn of a full panorama); ``x`` itself when ``k == 0``."""
    return np.roll(x, k, axis=1) if k else x


def _to_tensor(images: list[np.ndarray]) -> torch.Tensor:
    """uint8 ``[H,W,3]`` frames -> float32 ``[B,3,H,W]`` in [0, 1]."""
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float().div_(255.0)


def _prefetch(pool: ThreadPoolExecutor, fn: Any, items: Sequence[Any], ahead: int = 4) -> Iterable[Any]:
    """``fn(item)`` for each item in order, computed in ``pool`` at most ``ahead`` items in advance (so
    memory stays bounded, unlike ``pool.map``, which submits everything at once)."""
    pending: deque[Any] = deque()
    it = iter(items)
    for item in it:
        pending.append(pool.submit(fn, item))
        if len(pending) >= ahead:
            break
    while pending:
        yield pending.popleft().result()
        for item in it:
            pending.append(pool.submit(fn, item))
            break


def _progress(total: int, desc: str, progress: bool | None):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=(None if progress is None else not progress), leave=False)


# --------------------------------------------------------------------------------------- evaluation
def evaluate_depth(
    predictor_or_predictions: Any,
    data_root: PathLike,
    split: str | PathLike | None = "test",
    split_name: str = "default",
    prior_split: str | PathLike | None = "train",
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    median_scaling: bool = True,
    batch_size: int = 8,
    prior_max_frames: int | None = 2000,
    progress: bool | None = False,
    seam_fraction: float = 0.125,
    yaw_roll: int | None = None,
) -> dict[str, Any]:
    """Evaluate depth on a dataset's ground truth, with the ``constant`` and ``per_row`` baselines.

    Ground truth is read at its stored (native) size without augmentation; frames are the targets listed
    in ``split`` (every frame for ``None``) that have a depth file; sequences with ``mask.png`` are scored
    on its white pixels only.

    Args:
        predictor_or_predictions: a :class:`cylsfm.model.Predictor` (its depth comes back at the
            input's resolution; for a model trained on a crop of the panorama (``fov < 360``) the ground
            truth is cropped to the same columns), or a directory of predictions: one ``.npy`` depth map
            per frame, named after the frame's image, as ``PRED/SEQ/FRAME.npy`` or
            ``PRED/SEQ/depth/FRAME.npy`` (the first found; for a dataset that is a single sequence also
            ``PRED/FRAME.npy``). Shapes ``[h,w]`` (or ``[1,h,w]``, ``[1,1,h,w]``) of any size, resized to
            the ground truth bilinearly (across the seam of full panoramas when the width ratio is whole).
            Values are depths (not disparities) in any units.
        data_root: the dataset root.
        split: ``"test"``, ``"val"``, ``"train"``, a split file, or ``None`` (every frame).
        split_name: the split directory under ``ROOT/splits``.
        prior_split: the frames of the ``per_row`` prior (``None``: every frame of the dataset, which is
            optimistic when it includes the evaluated frames).
        min_depth, max_depth: valid ground-truth range (metres); see the module docstring.
        median_scaling: scale each prediction by ``median(gt) / median(pred)``. The baselines have no scale
            of their own and are always median-scaled.
        batch_size: images per network call.
        prior_max_frames: at most this many prior frames, evenly spaced in dataset order (``None``: all).
        progress: show progress bars (``None``: when stderr is a terminal).
        seam_fraction: on full 360-degree panoramas, also score the columns next to the seam (this share
            of the width, half at each side; default 1/8: 22.5 degrees each side) and, as a control, as
            many columns around the image centre, with each image's scale from the whole image. ``0``:
            off. Models trained on crops of the panorama have no seam.
        yaw_roll: a seed: roll every evaluated panorama, its ground truth and mask by a random number of
            columns (drawn per frame), as if the 360-degree camera had been turned about its vertical
            axis. A network that wraps around sees the same scene at another azimuth; one that does not
            may have learned where the road usually is in the image. Full panoramas and models only.

    Returns:
        ``{"model": metrics, "constant": metrics, "per_row": metrics or None, "n_images": int,
        "n_without_gt": int, "prior_images": int, "source": str, "data": str, "split": ..., "split_name",
        "prior_split", "min_depth", "max_depth", "median_scaling", "seam_fraction"}``; ``metrics`` as
        returned by :func:`evaluate_depth_maps`, with ``"seam"`` and ``"centre"`` (see
        :meth:`DepthAccumulator.result`).
        ``per_row`` is ``None`` when the prior frames have no ground truth.

    Raises:
        DatasetError: a dataset or prediction file is missing or invalid (named), or no evaluated frame
            has ground-truth depth.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    root = Path(data_root)
    sequences = scan_dataset(root)
    single = (root / "camera.json").exists()
    entries = split_entries(root, split, split_name, sequences)
    frames = _frames_of(sequences, entries)
    with_gt = [(s, i) for s, i in frames if s.depth_path(i) is not None]
    if not with_gt:
        where = "" if split is None else f" in split {split}"
        raise DatasetError(f"{root}: no frame{where} has ground-truth depth (SEQ/depth/FRAME.npy)")

    pred_dirs: dict[str, tuple[Path, ...]] = {}
    predictor = None
    if isinstance(predictor_or_predictions, (str, os.PathLike)):
        pred_root = Path(predictor_or_predictions)
        if not pred_root.is_dir():
            raise DatasetError(f"{pred_root}: predictions directory not found")
        pred_dirs = {s.name: prediction_path(pred_root, s, single) for s in sequences}
        source = f"predictions {pred_root}"
        # every file must exist before anything is computed: fail fast, naming the first missing one
        for s, i in with_gt:
            dirs = pred_dirs[s.name]
            if not any((d / f"{s.images[i].stem}.npy").is_file() for d in dirs):
                raise DatasetError(f"{dirs[0] / (s.images[i].stem + '.npy')}: prediction not found")
    else:
        predictor = predictor_or_predictions
        source = f"checkpoint {getattr(getattr(predictor, 'models', None), 'path', '?')}"
    if yaw_roll is not None:
        if predictor is None:
            raise ValueError("yaw_roll applies to a model's predictions, not to a directory of predictions")
        for s in sequences:
            if not s.camera.wraps and any(f[0] is s for f in with_gt):
                raise DatasetError(f"{s.path / 'camera.json'}: yaw rolls need full 360-degree panoramas")
        source += f", rolled by random yaws (seed {yaw_roll})"

    # ---- the per-row prior from the training frames
    prior = RowPrior(min_depth, max_depth)
    prior_entries = split_entries(root, prior_split, split_name, sequences)
    prior_frames = [(s, i) for s, i in _frames_of(sequences, prior_entries) if s.depth_path(i) is not None]
    if prior_max_frames is not None and len(prior_frames) > prior_max_frames:
        pick = np.linspace(0, len(prior_frames) - 1, prior_max_frames).round().astype(int)
        prior_frames = [prior_frames[k] for k in pick]
    seq_masks: dict[str, np.ndarray | None] = {}

    def mask_of(seq: SequenceInfo) -> np.ndarray | None:
        if seq.name not in seq_masks:
            seq_masks[seq.name] = None if seq.mask is None else load_mask(seq.mask)
        return seq_masks[seq.name]

    with ThreadPoolExecutor(max_workers=4) as pool:
        bar = _progress(len(prior_frames), "per-row prior", progress)
        for (seq, _), depth in zip(
            prior_frames,
            _prefetch(pool, lambda f: load_depth(f[0].depth_path(f[1])), prior_frames, 16),
            strict=True,
        ):
            prior.add(depth, mask_of(seq))
            bar.update()
        bar.close()

        # ---- the evaluated frames, a batch at a time within a sequence
        model = DepthAccumulator(min_depth, max_depth, median_scaling, seam_fraction)
        constant = DepthAccumulator(min_depth, max_depth, True, seam_fraction)
        per_row = DepthAccumulator(min_depth, max_depth, True, seam_fraction)
        have_prior = prior.medians() is not None
        batches: list[list[tuple[SequenceInfo, int]]] = []
        for seq in sequences:
            mine = [f for f in with_gt if f[0] is seq]
            batches += [mine[k : k + batch_size] for k in range(0, len(mine), batch_size)]

        seq_number = {id(s): k for k, s in enumerate(sequences)}

        def roll_of(seq: SequenceInfo, i: int) -> int:
            """Columns that frame ``i`` of ``seq`` is rolled by (0 without ``yaw_roll``)."""
            if yaw_roll is None:
                return 0
            rng = np.random.default_rng([yaw_roll, seq_number[id(seq)], i])
            return int(rng.integers(seq.camera.width))

        def load_batch(batch: list[tuple[SequenceInfo, int]]) -> tuple[list[np.ndarray], list[np.ndarray]]:
            seq = batch[0][0]
            rolls = [roll_of(seq, i) for _, i in batch]
            gts = [
                _roll_columns(load_depth(seq.depth_path(i)), k)
                for (_, i), k in zip(batch, rolls, strict=True)
            ]
            if predictor is not None:
                preds = [
                    _roll_columns(load_image(seq.images[i]), k)
                    for (_, i), k in zip(batch, rolls, strict=True)
                ]
            else:
                preds = [load_prediction(pred_dirs[seq.name], seq.images[i].stem) for _, i in batch]
            return gts, preds

        bar = _progress(len(with_gt), "depth", progress)
        for batch, (gts, preds) in zip(batches, _prefetch(pool, load_batch, batches), strict=True):
            seq = batch[0][0]
            camera = seq.camera
            mask = mask_of(seq)
            masks = [None if mask is None else _roll_columns(mask, roll_of(seq, i)) for _, i in batch]
            seam = camera.wraps
            if predictor is not None:
                depth = predictor.depth(_to_tensor(preds), camera)[:, 0].double().cpu().numpy()
                win = predictor.window(camera)
                if win is not None:
                    seam = False  # a crop of the panorama: its sides are no seam
                    gts = [g[:, win[0] : win[1]] for g in gts]
                    masks = [None if m is None else m[:, win[0] : win[1]] for m in masks]
                preds = list(depth)
            else:
                preds = [resize_depth(p, g.shape, wrap=camera.wraps) for p, g in zip(preds, gts, strict=True)]
            for (_, i), g, p, mask in zip(batch, gts, preds, masks, strict=True):
                try:
                    model.add(g, p, mask, seam)
                except ValueError as exc:
                    name = seq.images[i].stem
                    where = (
                        f"{seq.name}/{name}"
                        if predictor is not None
                        else str(pred_dirs[seq.name][0] / f"{name}.npy")
                    )
                    raise DatasetError(f"{where}: {exc}") from None
                constant.add(g, np.ones_like(g), mask, seam)
                if have_prior:
                    per_row.add(g, prior.depth_map(*g.shape), mask, seam)
            bar.update(len(batch))
        bar.close()

    result_model = model.result()
    return {
        "model": result_model,
        "constant": constant.result(),
        "per_row": per_row.result() if have_prior else None,
        "n_images": result_model["n_images"],
        "n_without_gt": len(frames) - len(with_gt) + model.skipped,
        "prior_images": prior.n_images,
        "source": source,
        "data": str(root),
        "split": None if split is None else str(split),
        "split_name": split_name,
        "prior_split": None if prior_split is None else str(prior_split),
        "min_depth": float(min_depth),
        "max_depth": float(max_depth),
        "median_scaling": bool(median_scaling),
        "seam_fraction": float(seam_fraction),
        "yaw_roll": yaw_roll,
    }


# --------------------------------------------------------------------------------------- reporting
def _metrics_only(m: dict[str, Any] | None) -> dict[str, Any] | None:
    if m is None:
        return None
    out = {k: m[k] for k in (*DEPTH_METRICS, "n_images", "scale_mean", "scale_std")}
    out["seam"] = m.get("seam")
    out["centre"] = m.get("centre")
    return out


def depth_json(result: dict[str, Any]) -> dict[str, Any]:
    """The JSON layout of a result of :func:`evaluate_depth`::

    {"abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3", "n_images", "scale_mean", "scale_std",
     "seam": {"abs_rel", ..., "a3", "n_images"} or null, "centre": {same keys} or null,
     "baselines": {"constant": {same keys}, "per_row": {same keys} or null},
     "meta": {"source", "data", "split", "split_name", "prior_split", "prior_images", "n_without_gt",
              "min_depth", "max_depth", "median_scaling", "seam_fraction", "yaw_roll"}}

    ``seam``: the measures over the columns next to the seam of full panoramas only; ``centre``: over as
    many columns around the image centre, opposite the seam (null when none was scored).
    """
    out: dict[str, Any] = dict(_metrics_only(result["model"]) or {})
    out["baselines"] = {
        "constant": _metrics_only(result["constant"]),
        "per_row": _metrics_only(result["per_row"]),
    }
    out["meta"] = {
        k: result[k]
        for k in (
            "source",
            "data",
            "split",
            "split_name",
            "prior_split",
            "prior_images",
            "n_without_gt",
            "min_depth",
            "max_depth",
            "median_scaling",
            "seam_fraction",
            "yaw_roll",
        )
        if k in result
    }
    return out


def _fmt(v: Any, width: int = 9) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-".rjust(width)
    return f"{v:{width}.4f}"


def format_depth_table(result: dict[str, Any]) -> str:
    """A readable table of a result of :func:`evaluate_depth`: model and baselines, then the ratios
    model / baseline (below 1 is better for the errors, above 1 for ``a1..a3``)."""
    head = f"{'':18}" + "".join(f"{k:>9}" for k in DEPTH_METRICS) + f"{'scale':>10}{'+-':>9}"
    lines = [
        f"depth: {result['n_images']} images ({result['source']}, split {result['split'] or 'all'}); "
        f"lower is better for abs_rel..rmse_log, higher for a1..a3",
        head,
    ]
    rows = [("model", result["model"]), ("constant", result["constant"]), ("per_row", result["per_row"])]
    for name, m in rows:
        if m is None:
            lines.append(f"{name:18}" + "(no training ground truth)")
            continue
        lines.append(
            f"{name:18}"
            + "".join(_fmt(m[k]) for k in DEPTH_METRICS)
            + _fmt(m["scale_mean"], 10)
            + _fmt(m["scale_std"])
        )
    for name, m in rows[1:]:
        if m is None:
            continue
        ratios = [
            (result["model"][k] / m[k]) if m[k] not in (0, None) and math.isfinite(m[k]) else None
            for k in DEPTH_METRICS
        ]
        lines.append(f"{'model/' + name:18}" + "".join(_fmt(r) for r in ratios))
    seams = [(name, m) for name, m in rows if m is not None and m.get("seam")]
    if seams:
        deg = 360.0 * result.get("seam_fraction", 0.0) / 2
        lines.append(
            f"next to the seam and, opposite it, around the centre ({deg:g} degrees each side, "
            f"{seams[0][1]['seam']['n_images']} images):"
        )
        for part in ("seam", "centre"):
            for name, m in seams:
                if m.get(part):
                    lines.append(
                        f"{name + ' @' + part:18}" + "".join(_fmt(m[part][k]) for k in DEPTH_METRICS)
                    )
    return "\n".join(lines)
