"""Removal of frames taken while the camera stood still, before snippets are formed.

:func:`kept_runs` splits a sequence into runs of consecutive good frames (bad frames break a run) and keeps,
within each run, the frames that moved enough since the last kept one: by the ground-truth camera centres
(metres) or by the mean grey-level difference of small thumbnails.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import InputError
from .format import DatasetError, DatasetWarning, SequenceInfo

__all__ = ["StaticFilter", "kept_runs"]

_THUMB_WIDTH = 64


@dataclass(frozen=True)
class StaticFilter:
    """Removal of frames taken while the camera stood still, before snippets are formed.

    A frame is kept when it moved enough relative to the last kept frame (the first frame is kept).

    Attributes:
        method: ``"poses"``: camera-centre distance from the ground-truth poses, at least
            ``min_translation`` metres (the paper's method); ``"image"``: mean absolute difference of
            downsampled grey frames in ``[0, 1]``, at least ``min_image_diff`` (decodes every frame once
            when the dataset is built); ``"auto"``: poses where a sequence has them, else images;
            ``"none"``: keep every frame.
        min_translation: metres between consecutive kept frames.
        min_image_diff: mean absolute grey difference between consecutive kept frames.

    Raises:
        InputError: for an unknown method or a negative threshold.
    """

    method: str = "auto"
    min_translation: float = 0.05
    min_image_diff: float = 0.01

    def __post_init__(self) -> None:
        if self.method not in ("auto", "poses", "image", "none"):
            raise InputError(f"static filter method must be auto, poses, image or none, got {self.method!r}")
        if self.min_translation < 0 or self.min_image_diff < 0:
            raise InputError("static filter thresholds must be non-negative")


def kept_runs(
    seq: SequenceInfo, static: StaticFilter, skip_bad: bool, stacklevel: int = 2
) -> list[list[int]]:
    """Runs of good frames of ``seq`` (frame indices in time order) with static frames removed.

    With the image method every good frame is decoded once (as a thumbnail). A frame that fails to decode
    raises :class:`DatasetError`, or with ``skip_bad`` is recorded in ``seq.bad`` with a
    :class:`DatasetWarning` (``stacklevel`` as seen from the caller of this function).
    """
    method = static.method
    if method == "auto":
        method = "poses" if seq.poses is not None else "image"
    if method == "poses" and seq.poses is None:
        raise DatasetError(
            f"{seq.path / 'poses.txt'}: not found (static filter 'poses' needs ground-truth poses)"
        )
    thumbs = _thumbnails(seq, skip_bad, stacklevel + 1) if method == "image" else {}
    runs = _runs(len(seq), set(seq.bad))
    if method == "none":
        return runs
    out = []
    for run in runs:
        if method == "poses":
            centres = seq.poses[run, :3, 3]
            pos = _keep_moving(
                lambda a, b, c=centres: float(np.linalg.norm(c[b] - c[a])), len(run), static.min_translation
            )
        else:
            th = [thumbs[i] for i in run]
            pos = _keep_moving(
                lambda a, b, th=th: float(np.abs(th[b] - th[a]).mean()), len(run), static.min_image_diff
            )
        out.append([run[p] for p in pos])
    return out


def _thumbnails(seq: SequenceInfo, skip_bad: bool, stacklevel: int) -> dict[int, np.ndarray]:
    """Grey thumbnails of the good frames of ``seq`` by index, decoded in a few threads."""
    todo = [i for i in range(len(seq)) if i not in seq.bad]
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
        results = list(pool.map(_try_thumbnail, [seq.images[i] for i in todo]))
    thumbs: dict[int, np.ndarray] = {}
    for i, res in zip(todo, results, strict=True):
        if isinstance(res, DatasetError):
            if not skip_bad:
                raise res
            warnings.warn(f"{res}; frame skipped", DatasetWarning, stacklevel=stacklevel + 1)
            seq.bad[i] = str(res)
        else:
            thumbs[i] = res
    return thumbs


def _grey_thumbnail(path: Path) -> np.ndarray:
    """``float32 [h, 64]`` grey version of an image in ``[0, 1]`` (area downsampled)."""
    try:
        with Image.open(path) as im:
            w, h = im.size
            tw = min(_THUMB_WIDTH, w)
            th = max(1, round(h * tw / w))
            im.draft("L", (tw, th))
            grey = im.convert("L").resize((tw, th), Image.Resampling.BOX)
            return np.asarray(grey, dtype=np.float32) / 255.0
    except Exception as exc:
        raise DatasetError(f"{path}: cannot decode image ({exc or type(exc).__name__})") from None


def _try_thumbnail(path: Path) -> np.ndarray | DatasetError:
    try:
        return _grey_thumbnail(path)
    except DatasetError as exc:
        return exc


def _keep_moving(distance: Callable[[int, int], float], count: int, threshold: float) -> list[int]:
    """Positions kept when each must be at least ``threshold`` away (``distance(i, j)``) from the last kept."""
    kept = [0] if count else []
    for i in range(1, count):
        if distance(kept[-1], i) >= threshold:
            kept.append(i)
    return kept


def _runs(n: int, bad: set[int]) -> list[list[int]]:
    """Maximal runs of consecutive good frames."""
    runs: list[list[int]] = []
    current: list[int] = []
    for i in range(n):
        if i in bad:
            if current:
                runs.append(current)
            current = []
        else:
            current.append(i)
    if current:
        runs.append(current)
    return runs
