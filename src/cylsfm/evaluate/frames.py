"""What the depth and the pose evaluations share: the frames of a split, images as network input, reading
ahead in a thread pool, the seeded yaw rolls of full panoramas, and the checks of the common options.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch

from ..data import DatasetError, SequenceInfo, load_image
from ..data.splits import SPLIT_PARTS, read_split, split_path
from ..errors import InputError
from ..geometry import roll_columns

__all__ = [
    "Frame",
    "PathLike",
    "check_batch_size",
    "check_rollable",
    "check_yaw_roll",
    "draw_roll",
    "frames_of",
    "load_images",
    "model_source",
    "prefetch",
    "split_entries",
]

PathLike = str | os.PathLike[str]

#: One frame of a dataset: its sequence and its index in the sequence.
Frame = tuple[SequenceInfo, int]

T = TypeVar("T")
R = TypeVar("R")


# --------------------------------------------------------------------------------------- frames
def split_entries(
    root: PathLike, split: str | PathLike | None, split_name: str, sequences: Sequence[SequenceInfo]
) -> list[tuple[str, str]] | None:
    """The ``(sequence, frame)`` entries of a split, or ``None`` for ``split=None`` (every frame).

    ``split`` is ``"train"``, ``"val"`` or ``"test"`` (``ROOT/splits/<split_name>/<split>.txt``) or the
    path of a split file.

    Raises:
        DatasetError: the split file does not exist or names frames that the dataset does not have.
    """
    if split is None:
        return None
    if isinstance(split, str) and split in SPLIT_PARTS:
        path = split_path(root, split, split_name)
        if not path.exists():
            raise DatasetError(
                f"{path}: split file not found (write the splits with `cylsfm split {root}`, or use --split all)"
            )
    else:
        path = Path(split)
    return read_split(path, root, sequences)


def frames_of(sequences: Sequence[SequenceInfo], entries: list[tuple[str, str]] | None) -> list[Frame]:
    """The frames of split ``entries`` (every good frame for ``None``), in dataset order, each once."""
    if entries is None:
        return [(s, i) for s in sequences for i in range(len(s)) if i not in s.bad]
    wanted = {(a, b) for a, b in entries}
    return [(s, i) for s in sequences for i, stem in enumerate(s.stems) if (s.name, stem) in wanted]


# --------------------------------------------------------------------------------------- images
def load_images(paths: Sequence[Path], rolls: int | Sequence[int] = 0) -> torch.Tensor:
    """Load frames as network input: float32 ``[B,3,H,W]`` in ``[0, 1]``.

    Args:
        paths: ``B`` image files of one size.
        rolls: roll every frame by this many columns (one number for all, or one per frame), as if the
            360-degree camera had been turned about its vertical axis (:func:`cylsfm.geometry.roll_columns`).
    """
    ks = [rolls] * len(paths) if isinstance(rolls, int) else list(rolls)
    frames = [roll_columns(load_image(p), k, axis=1) for p, k in zip(paths, ks, strict=True)]
    return torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2).float().div_(255.0)


def prefetch(
    pool: ThreadPoolExecutor, fn: Callable[[T], R], items: Sequence[T], ahead: int = 4
) -> Iterator[R]:
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


# --------------------------------------------------------------------------------------- yaw rolls
def draw_roll(width: int, seed: int, *keys: int) -> int:
    """A roll in ``[0, width)`` columns drawn from the generator seeded with ``[seed, *keys]``: the same
    seed and keys (a sequence's number, a frame's index) always give the same roll."""
    return int(np.random.default_rng([seed, *keys]).integers(width))


def check_rollable(sequences: Sequence[SequenceInfo]) -> None:
    """Raise :class:`DatasetError` naming the camera of the first sequence that is no full panorama."""
    for s in sequences:
        if not s.camera.wraps:
            raise DatasetError(f"{s.path / 'camera.json'}: yaw rolls need full 360-degree panoramas")


# --------------------------------------------------------------------------------------- options
def check_batch_size(batch_size: int) -> None:
    """Raise :class:`InputError` unless ``batch_size >= 1``."""
    if not batch_size >= 1:
        raise InputError(f"batch_size must be >= 1, got {batch_size}")


def check_yaw_roll(yaw_roll: int | None, given: Any, what: str) -> None:
    """Raise :class:`InputError` when ``yaw_roll`` is given with stored results (``given`` is a path,
    described as ``what`` in the message) instead of a model."""
    if yaw_roll is not None and isinstance(given, (str, os.PathLike)):
        raise InputError(f"yaw_roll applies to a model's predictions, not to {what}")


def model_source(predictor: Any) -> str:
    """``"checkpoint PATH"``: the description of a predictor's results."""
    return f"checkpoint {getattr(getattr(predictor, 'models', None), 'path', '?')}"
