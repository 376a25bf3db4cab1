"""Where the scored depth comes from: a model (:class:`cylsfm.model.Predictor`) run on the panoramas, or a
directory of stored predictions (``PRED/SEQ/FRAME.npy``, ``PRED/SEQ/depth/FRAME.npy`` or, for a dataset that
is one sequence, ``PRED/FRAME.npy``), each with the ground truth at the same size.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data import DatasetError, SequenceInfo, load_depth
from ..geometry import roll_columns
from .depth_metrics import as_depth_map, resize_depth
from .frames import Frame, PathLike, check_rollable, load_images, model_source

__all__ = ["DepthSource", "Rolled", "load_prediction", "open_depth_source", "prediction_path"]

#: A frame to score and the columns its panorama is rolled by (0 without yaw rolls).
Rolled = tuple[SequenceInfo, int, int]


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
        out = as_depth_map(arr, "prediction")
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from None
    if not np.all(np.isfinite(out)):
        raise DatasetError(f"{path}: prediction has non-finite values (NaN or inf)")
    return out


@dataclass
class DepthSource:
    """Where the scored depth comes from: a predictor (``dirs`` empty) or a directory of predictions
    (``dirs``: sequence name -> the directories of :func:`prediction_path`). ``source`` describes it."""

    predictor: Any | None
    dirs: dict[str, tuple[Path, ...]]
    source: str

    def load(self, batch: list[Rolled]) -> tuple[list[np.ndarray], Any]:
        """Ground truth ``[H,W]`` of a batch of one sequence, and the network input ``[B,3,H,W]`` or the
        stored predictions, all rolled as the batch says (run in a worker thread)."""
        seq = batch[0][0]
        gts = [roll_columns(load_depth(seq.depth_path(i)), k, axis=1) for _, i, k in batch]
        if self.predictor is not None:
            return gts, load_images([seq.images[i] for _, i, _ in batch], [k for _, _, k in batch])
        return gts, [load_prediction(self.dirs[seq.name], seq.images[i].stem) for _, i, _ in batch]

    def depths(self, seq: SequenceInfo, loaded: Any, gts: list, masks: list) -> tuple[list, list, list, bool]:
        """``(predictions, ground truth, masks, seam)`` at the same size: the network's depth with the
        ground truth and masks cropped to its window, or the stored predictions resized to the ground
        truth. ``seam``: the images are full panoramas (a crop's sides are no seam)."""
        camera = seq.camera
        if self.predictor is None:
            return (
                [resize_depth(p, g.shape, wrap=camera.wraps) for p, g in zip(loaded, gts, strict=True)],
                gts,
                masks,
                camera.wraps,
            )
        mask = None  # the occluder fixed to the camera, filled in what the network sees
        if any(m is not None for m in masks):
            ones = np.ones(loaded.shape[-2:], np.float32)
            mask = torch.from_numpy(np.stack([ones if m is None else m for m in masks]).astype(np.float32))
            mask = mask[:, None]
        masked = {"mask": mask} if mask is not None else {}
        preds = list(self.predictor.depth(loaded, camera, **masked)[:, 0].double().cpu().numpy())
        win = self.predictor.window(camera)
        if win is None:
            return preds, gts, masks, camera.wraps
        gts = [g[:, win[0] : win[1]] for g in gts]
        masks = [None if m is None else m[:, win[0] : win[1]] for m in masks]
        return preds, gts, masks, False

    def where(self, seq: SequenceInfo, i: int) -> str:
        """The frame, or its prediction file, in messages."""
        stem = seq.images[i].stem
        return (
            f"{seq.name}/{stem}"
            if self.predictor is not None
            else str(self.dirs[seq.name][0] / f"{stem}.npy")
        )


def open_depth_source(
    given: Any, root: Path, sequences: list[SequenceInfo], with_gt: list[Frame], yaw_roll: int | None = None
) -> DepthSource:
    """The depth source of :func:`cylsfm.evaluate.depth.evaluate_depth` for ``given`` (a predictor or a
    directory of predictions).

    A directory must hold a prediction for every frame of ``with_gt``: checked before anything is computed,
    naming the first missing file. With ``yaw_roll`` (models only) the sequences of ``with_gt`` must be full
    panoramas.

    Raises:
        DatasetError: the directory or a prediction file is missing, or a rolled sequence is no panorama.
    """
    if not isinstance(given, (str, os.PathLike)):
        source = DepthSource(given, {}, model_source(given))
        if yaw_roll is not None:
            check_rollable([s for s in sequences if any(f[0] is s for f in with_gt)])
            source.source += f", rolled by random yaws (seed {yaw_roll})"
        return source
    pred_root = Path(given)
    if not pred_root.is_dir():
        raise DatasetError(f"{pred_root}: predictions directory not found")
    single = (root / "camera.json").exists()
    dirs = {s.name: prediction_path(pred_root, s, single) for s in sequences}
    for s, i in with_gt:
        if not any((d / f"{s.images[i].stem}.npy").is_file() for d in dirs[s.name]):
            raise DatasetError(f"{dirs[s.name][0] / (s.images[i].stem + '.npy')}: prediction not found")
    return DepthSource(None, dirs, f"predictions {pred_root}")
