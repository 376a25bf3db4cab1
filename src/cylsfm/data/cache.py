"""Frames decoded once: a dataset's frames at the training size, kept in memory as ``uint8``.

Training draws every frame many times (each is the target of one snippet and a source of others, every
epoch). Decoding and resampling it each time costs more CPU than the networks' own step on small images,
and on a two-core machine that CPU is taken from the step. :class:`FrameCache` decodes each frame once
(2400 frames at 256x64 are 118 MB) and hands out views of one array; loader worker processes share it
copy-on-write.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

import numpy as np

from ..runtime import progress_bar

__all__ = ["FrameCache", "available_memory_bytes"]


def available_memory_bytes() -> int | None:
    """Memory the system can still give (bytes), or ``None`` where it cannot tell."""
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


class FrameCache:
    """Decoded frames ``uint8 [H,W,3]`` addressed by ``(sequence, frame)`` index pairs.

    Args:
        keys: the ``(sequence index, frame index)`` pairs to hold, each once.
        shape: ``(H, W)`` every frame has after decoding.
        decode: ``decode(sequence, frame) -> uint8 [H,W,3]``; an exception propagates (the caller decides
            whether a bad frame is fatal) and leaves the frame out.
        progress: show a progress bar (``None``: only on a terminal).
    """

    def __init__(
        self,
        keys: Sequence[tuple[int, int]],
        shape: tuple[int, int],
        decode: Callable[[int, int], np.ndarray],
        progress: bool | None = None,
    ) -> None:
        self.frames = np.empty((len(keys), shape[0], shape[1], 3), dtype=np.uint8)
        self.slot: dict[tuple[int, int], int] = {}
        self.failed: dict[tuple[int, int], Exception] = {}
        bar = progress_bar(keys, total=len(keys), desc="decoding frames", unit="frame", enabled=progress)
        for key in bar:
            try:
                image = decode(*key)
            except Exception as exc:  # kept to be raised where the frame is used
                self.failed[key] = exc
                continue
            self.frames[len(self.slot)] = image
            self.slot[key] = len(self.slot)
        self.frames = self.frames[: len(self.slot)]

    @staticmethod
    def nbytes(n_frames: int, shape: tuple[int, int]) -> int:
        """Bytes that ``n_frames`` frames of ``shape = (H, W)`` take."""
        return n_frames * shape[0] * shape[1] * 3

    def get(self, sequence: int, frame: int) -> np.ndarray:
        """The decoded frame ``uint8 [H,W,3]`` (a read-only view); re-raises its decoding error."""
        key = (sequence, frame)
        if key in self.failed:
            raise self.failed[key]
        view = self.frames[self.slot[key]]
        view.flags.writeable = False
        return view
