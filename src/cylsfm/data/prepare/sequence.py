"""A sequence written by ``cylsfm prepare``: resumable, idempotent, and honest about what it read.

Frames are written atomically as ``images/FRAME.png`` under their source's name (a video frame's 6-digit
index in the video, an image's stem), so that a second run finds the frames already written and skips
them. ``prepare.json`` holds the settings (a run with other settings does not continue another's
work), how many frames were read of how many the source announced, and whether the source broke off.
``camera.json`` is written last: a sequence without it is unfinished (:mod:`cylsfm.data.format`).
"""

from __future__ import annotations

import json
import os
import shutil
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from ...atomic import atomic_write_text
from ...errors import CylsfmError
from ...geometry import Camera
from ...runtime import fingerprint
from ..format import IMAGE_SUFFIXES
from ..io import save_depth, save_png, write_tum

__all__ = ["PREPARE_FILE", "PreparedSequence"]

#: The preparation's record in each sequence directory.
PREPARE_FILE = "prepare.json"
#: zlib level of prepared frames: 1 writes a 2048x512 frame 2-3x faster than the default 6 for files about
#: 15-30% larger (BENCHMARKS.md); decoding them costs the same.
PNG_LEVEL = 1
_WRITERS = 2


class PreparedSequence:
    """One output sequence of ``cylsfm prepare``.

    Args:
        path: the sequence directory.
        camera: the output frames' camera.
        settings: what decides the output (JSON-serialisable): a directory prepared with other settings is
            refused unless ``overwrite``.
        overwrite: start over, removing what a previous preparation wrote there.

    Raises:
        CylsfmError: the directory holds another preparation or a sequence not written by ``prepare``.
    """

    def __init__(
        self, path: str | os.PathLike[str], camera: Camera, settings: dict[str, Any], overwrite: bool
    ) -> None:
        self.path = Path(path)
        self.camera = camera
        self.key = fingerprint(settings)
        self.record: dict[str, Any] = {"settings": settings, "key": self.key, "finished": False}
        record = self.path / PREPARE_FILE
        if overwrite and self.path.exists():
            shutil.rmtree(self.path)
        elif record.is_file():
            old = _read_record(record)
            if old.get("key") != self.key:
                raise CylsfmError(
                    f"{self.path}: prepared with other settings ({record}); --overwrite starts it again"
                )
            self.record = old
        elif (self.path / "camera.json").exists() or (self.path / "images").is_dir():
            raise CylsfmError(
                f"{self.path}: holds a sequence that cylsfm prepare did not write; --overwrite replaces it"
            )
        if (
            not record.is_file()
        ):  # claimed before the first frame: an interrupted run is continued, not refused
            self.path.mkdir(parents=True, exist_ok=True)
            atomic_write_text(record, json.dumps(self.record, indent=2) + "\n")
        (self.path / "images").mkdir(parents=True, exist_ok=True)
        self.done = {p.stem for p in (self.path / "images").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
        self._writer: ThreadPoolExecutor | None = None
        self._pending: deque[Future[None]] = deque()

    @property
    def finished(self) -> bool:
        """Whether a previous run finished this sequence (nothing left to do)."""
        return bool(self.record.get("finished")) and (self.path / "camera.json").is_file()

    def has(self, frame: str) -> bool:
        """Whether frame ``frame`` is written already."""
        return frame in self.done

    def add(self, frame: str, image: np.ndarray, depth: np.ndarray | None = None) -> None:
        """Write ``images/FRAME.png`` (``uint8 [H,W,3]`` of the camera's size) atomically, and
        ``depth/FRAME.npy`` when ``depth`` (``float32 [H,W]`` metres, 0 unknown) is given.

        PNG compression (the slowest step of preparing) runs on writer threads while the next frames are
        decoded; :meth:`wait` (called by :meth:`finish`) waits for them and raises their errors.
        """
        w, h = self.camera.size
        if image.shape != (h, w, 3) or image.dtype != np.uint8:
            raise CylsfmError(
                f"{self.path}: frame {frame} is {image.dtype} {image.shape}, expected uint8 ({h},{w},3)"
            )
        if self._writer is None:
            self._writer = ThreadPoolExecutor(max_workers=_WRITERS, thread_name_prefix="cylsfm-png")
        while len(self._pending) >= 2 * _WRITERS:  # bounded: at most a few frames in memory
            self._pending.popleft().result()
        if depth is not None:
            if depth.shape != (h, w):
                raise CylsfmError(f"{self.path}: depth of frame {frame} is {depth.shape}, expected ({h},{w})")
            (self.path / "depth").mkdir(exist_ok=True)
            save_depth(self.path / "depth" / f"{frame}.npy", depth)  # before the image: a frame is complete
        path = self.path / "images" / f"{frame}.png"
        self._pending.append(self._writer.submit(save_png, path, image, PNG_LEVEL))
        self.done.add(frame)

    def wait(self) -> None:
        """Wait until every frame given to :meth:`add` is written (raising the first writer's error)."""
        try:
            while self._pending:
                self._pending.popleft().result()
        finally:
            if self._writer is not None:
                self._writer.shutdown(wait=True, cancel_futures=True)
                self._writer = None

    def last_frame(self) -> Path | None:
        """The last frame written so far (by name), or ``None``."""
        return self.path / "images" / f"{max(self.done)}.png" if self.done else None

    def note(self, **facts: Any) -> None:
        """Record facts about the source (frames read, expected, broke off ...) in ``prepare.json``."""
        self.record.update(facts)
        atomic_write_text(self.path / PREPARE_FILE, json.dumps(self.record, indent=2) + "\n")

    def finish(
        self, mask: np.ndarray | None = None, poses: dict[str, tuple[float, np.ndarray]] | None = None
    ) -> None:
        """Write ``mask.png`` (when given), ``poses.txt`` (``poses``: frame name -> (time in seconds,
        camera-to-world ``[4,4]``), for every frame written), ``camera.json`` last, and mark the
        preparation finished.

        Raises:
            CylsfmError: no frame was written.
        """
        self.wait()
        if not self.done:
            raise CylsfmError(f"{self.path}: no frames were written (every frame excluded or unreadable)")
        if mask is not None:
            save_png(self.path / "mask.png", np.where(mask, 255, 0).astype(np.uint8))
        if poses is not None:
            names = sorted(self.done)
            missing = [n for n in names if n not in poses]
            if missing:
                raise CylsfmError(f"{self.path}: no pose for frame {missing[0]}")
            write_tum(
                self.path / "poses.txt",
                [poses[n][0] for n in names],
                np.stack([poses[n][1] for n in names]),
                comments=["camera-to-world, metres (from the source's ground truth)"],
            )
        self.camera.to_json(self.path / "camera.json")
        self.note(finished=True, frames_written=len(self.done))


def _read_record(path: Path) -> dict[str, Any]:
    try:
        out = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CylsfmError(
            f"{path}: cannot read the preparation record ({exc}); --overwrite starts again"
        ) from None
    if not isinstance(out, dict):
        raise CylsfmError(f"{path}: not a preparation record; --overwrite starts again")
    return out
