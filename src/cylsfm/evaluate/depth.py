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

**What is scored.** Ground truth is read at its stored (native) size without augmentation. The depth comes
from a :class:`cylsfm.model.Predictor` (at the input's resolution; for a model trained on a crop of the
panorama, ``fov < 360``, the ground truth is cropped to the same columns) or from a directory of
predictions: one ``.npy`` depth map per frame, named after the frame's image, as ``PRED/SEQ/FRAME.npy`` or
``PRED/SEQ/depth/FRAME.npy`` (the first found; for a dataset that is a single sequence also
``PRED/FRAME.npy``). Stored predictions are ``[h,w]`` (or ``[1,h,w]``, ``[1,1,h,w]``) of any size, resized
to the ground truth bilinearly (across the seam of full panoramas when the width ratio is whole); their
values are depths (not disparities) in any units.

The measures and accumulators are in :mod:`cylsfm.evaluate.depth_metrics` (re-exported here). Depths are
in metres (ground truth) or network units (predictions, scaled away). Images are ``[H,W]``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data import DatasetError, SequenceInfo, load_depth, load_mask, scan_dataset
from ..geometry import roll_columns
from ..runtime import progress_bar
from .depth_metrics import (
    DEPTH_METRICS,
    DepthAccumulator,
    RowPrior,
    depth_errors,
    evaluate_depth_maps,
    resize_depth,
)
from .depth_source import DepthSource, Rolled, load_prediction, open_depth_source, prediction_path
from .frames import (
    Frame,
    PathLike,
    check_batch_size,
    check_yaw_roll,
    draw_roll,
    frames_of,
    prefetch,
    split_entries,
)
from .tables import ratio, text_row

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


# --------------------------------------------------------------------------------------- frames and masks
@dataclass
class _Masks:
    """The masks of the sequences (``[H,W]``, or ``None`` without ``mask.png``), each read once."""

    loaded: dict[str, np.ndarray | None] = field(default_factory=dict)

    def of(self, seq: SequenceInfo) -> np.ndarray | None:
        if seq.name not in self.loaded:
            self.loaded[seq.name] = None if seq.mask is None else load_mask(seq.mask)
        return self.loaded[seq.name]


def _with_depth(frames: list[Frame], root: Path, split: Any) -> list[Frame]:
    """The frames that have ground-truth depth; :class:`DatasetError` when none has."""
    with_gt = [(s, i) for s, i in frames if s.depth_path(i) is not None]
    if not with_gt:
        where = "" if split is None else f" in split {split}"
        raise DatasetError(f"{root}: no frame{where} has ground-truth depth (SEQ/depth/FRAME.npy)")
    return with_gt


def _batches(
    sequences: list[SequenceInfo], with_gt: list[Frame], batch_size: int, yaw_roll: int | None
) -> list[list[Rolled]]:
    """Batches of at most ``batch_size`` frames of one sequence, each frame with its roll: drawn per frame
    from ``[yaw_roll, sequence number, frame index]`` (0 without ``yaw_roll``)."""
    out: list[list[Rolled]] = []
    for n, seq in enumerate(sequences):
        width = seq.camera.width
        mine = [
            (s, i, 0 if yaw_roll is None else draw_roll(width, yaw_roll, n, i))
            for s, i in with_gt
            if s is seq
        ]
        out += [mine[k : k + batch_size] for k in range(0, len(mine), batch_size)]
    return out


# --------------------------------------------------------------------------------------- scoring
def _fit_prior(
    pool: ThreadPoolExecutor,
    frames: list[Frame],
    masks: _Masks,
    depth_range: tuple[float, float],
    progress: Any,
) -> RowPrior:
    """The per-row prior of ``frames`` (their ground truth read ahead in ``pool``)."""
    prior = RowPrior(*depth_range)
    bar = progress_bar(total=len(frames), desc="per-row prior", enabled=progress)
    for (seq, _), depth in zip(
        frames, prefetch(pool, lambda f: load_depth(f[0].depth_path(f[1])), frames, 16), strict=True
    ):
        prior.add(depth, masks.of(seq))
        bar.update()
    bar.close()
    return prior


def _prior_frames(
    root: Path, sequences: list[SequenceInfo], split: Any, split_name: str, max_frames: int | None
) -> list[Frame]:
    """The frames of the per-row prior with ground truth, at most ``max_frames`` evenly spaced ones."""
    frames = frames_of(sequences, split_entries(root, split, split_name, sequences))
    frames = [(s, i) for s, i in frames if s.depth_path(i) is not None]
    if max_frames is not None and len(frames) > max_frames:
        pick = np.linspace(0, len(frames) - 1, max_frames).round().astype(int)
        frames = [frames[k] for k in pick]
    return frames


@dataclass
class _Scores:
    """The accumulators of the model and of both baselines (always median-scaled)."""

    model: DepthAccumulator
    constant: DepthAccumulator
    per_row: DepthAccumulator
    #: per sequence: each frame's median-scaling factor of the model and of the constant depth (the
    #: reference that gives every frame its own scale: its factor is the frame's median true depth)
    scales: dict[str, list[tuple[float, float]]] = field(default_factory=dict)

    @classmethod
    def create(
        cls, min_depth: float, max_depth: float, median_scaling: bool, seam_fraction: float
    ) -> _Scores:
        return cls(
            DepthAccumulator(min_depth, max_depth, median_scaling, seam_fraction),
            DepthAccumulator(min_depth, max_depth, True, seam_fraction),
            DepthAccumulator(min_depth, max_depth, True, seam_fraction),
        )

    def add(
        self,
        gt: np.ndarray,
        pred: np.ndarray,
        mask: Any,
        seam: bool,
        prior: np.ndarray | None,
        where: str,
        ride: str = "",
    ) -> None:
        """Score one image of sequence ``ride`` (``prior``: the per-row map at its size, or ``None``); a
        prediction that cannot be scored is a :class:`DatasetError` naming ``where``."""
        try:
            own = self.model.add(gt, pred, mask, seam)
        except ValueError as exc:
            raise DatasetError(f"{where}: {exc}") from None
        reference = self.constant.add(gt, np.ones_like(gt), mask, seam)
        if own is not None and reference is not None:
            self.scales.setdefault(ride, []).append((own, reference))
        if prior is not None:
            self.per_row.add(gt, prior, mask, seam)

    def result(self, prior: RowPrior) -> dict[str, Any]:
        """``{"model", "constant", "per_row" (``None`` without prior), "n_images"}``."""
        model = self.model.result()
        per_row = self.per_row.result() if prior.medians() is not None else None
        return {
            "model": model,
            "constant": self.constant.result(),
            "per_row": per_row,
            "n_images": model["n_images"],
            "scale_consistency": scale_consistency(self.scales) if self.model.median_scaling else None,
        }


def _score(
    pool: ThreadPoolExecutor,
    batches: list[list[Rolled]],
    depths: DepthSource,
    masks: _Masks,
    prior: RowPrior,
    scores: _Scores,
    progress: Any,
) -> None:
    """Score every batch (read ahead in ``pool``) into ``scores``; masks are rolled with their frames."""
    prior_maps: dict[tuple[int, int], np.ndarray | None] = {}
    bar = progress_bar(total=sum(len(b) for b in batches), desc="depth", enabled=progress)
    for batch, (gts, loaded) in zip(batches, prefetch(pool, depths.load, batches), strict=True):
        seq = batch[0][0]
        mask = masks.of(seq)
        rolled = [None if mask is None else roll_columns(mask, k, axis=1) for _, _, k in batch]
        preds, gts, rolled, seam = depths.depths(seq, loaded, gts, rolled)
        for (_, i, _), g, p, m in zip(batch, gts, preds, rolled, strict=True):
            if g.shape not in prior_maps:
                prior_maps[g.shape] = prior.depth_map(*g.shape)
            scores.add(g, p, m, seam, prior_maps[g.shape], depths.where(seq, i), seq.name)
        bar.update(len(batch))
    bar.close()


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

    Frames are the targets listed in ``split`` that have a depth file; sequences with ``mask.png`` are
    scored on its white pixels only (protocol and prediction files: see the module docstring).

    Args:
        predictor_or_predictions: a :class:`cylsfm.model.Predictor`, or a directory of predictions.
        data_root: the dataset root.
        split: ``"test"``, ``"val"``, ``"train"``, a split file, or ``None`` (every frame).
        split_name: the split directory under ``ROOT/splits``.
        prior_split: the frames of the ``per_row`` prior (``None``: every frame of the dataset, which is
            optimistic when it includes the evaluated frames).
        min_depth, max_depth: valid ground-truth range (metres), ``0 < min_depth < max_depth``.
        median_scaling: scale each prediction by ``median(gt) / median(pred)`` (the baselines always are).
        batch_size: images per network call, at least 1.
        prior_max_frames: at most this many prior frames, evenly spaced in dataset order (``None``: all).
        progress: show progress bars (``None``: when stderr is a terminal).
        seam_fraction: in ``[0, 1]``: on full panoramas also score the columns next to the seam (this
            share of the width, half at each side; default 1/8: 22.5 degrees each side) and, as a control,
            as many columns around the image centre, with each image's scale from the whole image. ``0``:
            off. Models trained on crops of the panorama have no seam.
        yaw_roll: a seed: roll every evaluated panorama, its ground truth and mask by a random number of
            columns (drawn per frame), as if the camera had been turned about its vertical axis (a network
            that does not wrap around may have learned where the road usually is). Panoramas, models only.

    Returns:
        ``{"model", "constant", "per_row" (``None`` when the prior frames have no ground truth): metrics as
        returned by :func:`evaluate_depth_maps` with ``"seam"`` and ``"centre"``, "n_images",
        "n_without_gt", "prior_images", "source", "data", "split", "split_name", "prior_split", "min_depth",
        "max_depth", "median_scaling", "seam_fraction", "yaw_roll"}``; see :func:`depth_json`.

    Raises:
        InputError: an invalid argument (see above).
        DatasetError: a missing or invalid dataset or prediction file (named), or no frame with depth.
    """
    check_batch_size(batch_size)
    check_yaw_roll(yaw_roll, predictor_or_predictions, "a directory of predictions")
    scores = _Scores.create(min_depth, max_depth, median_scaling, seam_fraction)  # checks both
    root = Path(data_root)
    sequences = scan_dataset(root)
    frames = frames_of(sequences, split_entries(root, split, split_name, sequences))
    with_gt = _with_depth(frames, root, split)
    depths = open_depth_source(predictor_or_predictions, root, sequences, with_gt, yaw_roll)
    masks = _Masks()
    with ThreadPoolExecutor(max_workers=4) as pool:
        prior_frames = _prior_frames(root, sequences, prior_split, split_name, prior_max_frames)
        prior = _fit_prior(pool, prior_frames, masks, (min_depth, max_depth), progress)
        batches = _batches(sequences, with_gt, batch_size, yaw_roll)
        _score(pool, batches, depths, masks, prior, scores, progress)
    return {
        **scores.result(prior),
        "n_without_gt": len(frames) - len(with_gt) + scores.model.skipped,
        "prior_images": prior.n_images,
        "source": depths.source,
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


def scale_consistency(scales: dict[str, list[tuple[float, float]]]) -> dict[str, Any] | None:
    """How steady the depth's scale is over each ride: the coefficient of variation (standard deviation
    over mean) of the per-frame median-scaling factors, for the model and for the reference that gives every
    frame its own scale (a depth of median 1 in each frame: its factor is the frame's median true depth, as
    with panoramic depth models that normalise each panorama), per ride and averaged over the rides with at
    least two frames. Below the reference: the model keeps one scale over a ride better than per-frame
    normalisation would. ``None`` without such a ride."""
    rides = {}
    for name, pairs in scales.items():
        if len(pairs) < 2:
            continue
        arr = np.asarray(pairs, dtype=np.float64)
        cv = arr.std(axis=0) / np.abs(arr.mean(axis=0))
        rides[name] = {"model": float(cv[0]), "reference": float(cv[1]), "frames": len(pairs)}
    if not rides:
        return None
    return {
        "model": float(np.mean([r["model"] for r in rides.values()])),
        "reference": float(np.mean([r["reference"] for r in rides.values()])),
        "rides": rides,
    }


# --------------------------------------------------------------------------------------- reporting
def _metrics_only(m: dict[str, Any] | None) -> dict[str, Any] | None:
    if m is None:
        return None
    out = {k: m[k] for k in (*DEPTH_METRICS, "n_images", "scale_mean", "scale_std")}
    out["seam"] = m.get("seam")
    out["centre"] = m.get("centre")
    return out


#: The ``"meta"`` entries of :func:`depth_json`, in order.
_META = (
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


def depth_json(result: dict[str, Any]) -> dict[str, Any]:
    """The JSON layout of a result of :func:`evaluate_depth`::

    {"abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3", "n_images", "scale_mean", "scale_std",
     "seam": {"abs_rel", ..., "a3", "n_images"} or null, "centre": {same keys} or null,
     "baselines": {"constant": {same keys}, "per_row": {same keys} or null},
     "scale_consistency": {"model", "reference", "rides": {SEQ: {"model", "reference", "frames"}}} or null,
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
    out["scale_consistency"] = result.get("scale_consistency")
    out["meta"] = {k: result[k] for k in _META if k in result}
    return out


def format_depth_table(result: dict[str, Any]) -> str:
    """A readable table of a result of :func:`evaluate_depth`: model and baselines, then the ratios
    model / baseline (below 1 is better for the errors, above 1 for ``a1..a3``)."""
    widths = [9] * len(DEPTH_METRICS) + [10, 9]
    lines = [
        f"depth: {result['n_images']} images ({result['source']}, split {result['split'] or 'all'}); "
        f"lower is better for abs_rel..rmse_log, higher for a1..a3",
        text_row("", [*DEPTH_METRICS, "scale", "+-"], widths, 18),
    ]
    rows = [("model", result["model"]), ("constant", result["constant"]), ("per_row", result["per_row"])]
    for name, m in rows:
        if m is None:
            lines.append(f"{name:18}(no training ground truth)")
        else:
            lines.append(
                text_row(name, [*(m[k] for k in DEPTH_METRICS), m["scale_mean"], m["scale_std"]], widths, 18)
            )
    for name, m in rows[1:]:
        if m is not None:
            ratios = [ratio(result["model"][k], m[k]) for k in DEPTH_METRICS]
            lines.append(text_row(f"model/{name}", ratios, 9, 18))
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
                    lines.append(text_row(f"{name} @{part}", [m[part][k] for k in DEPTH_METRICS], 9, 18))
    sc = result.get("scale_consistency")
    if sc:
        lines.append(
            f"scale over each ride (coefficient of variation of the per-frame scale factors, {len(sc['rides'])} "
            f"rides): model {sc['model']:.4f}, a per-frame scale {sc['reference']:.4f} (lower: one scale per ride)"
        )
    return "\n".join(lines)
