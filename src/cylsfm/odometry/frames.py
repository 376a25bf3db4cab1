"""The ride that :func:`cylsfm.odometry` follows: a video file, a folder of images or a dataset sequence,
its frames in order with their times, its ground truth when it has one, and ground-truth depth from a
dataset (``depth_from``) for testing the refinement on its own."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data.format import SequenceInfo, load_image, scan_dataset
from ..data.inputs import discover_inputs, read_frames
from ..data.video import FALLBACK_RATE
from ..errors import CylsfmError, InputError
from ..geometry import Camera

__all__ = ["Ride", "depth_files", "open_ride"]


@dataclass
class Ride:
    """One input of :func:`cylsfm.odometry`.

    Attributes:
        path: the file or folder given.
        kind: ``"video"``, ``"folder"`` or ``"sequence"`` (a dataset sequence: ``camera.json`` and
            ``images/``, optionally ``poses.txt`` and ``depth/``).
        name: the input's name (file stem or folder name).
        size: the frames' size ``(W, H)``.
        frames: how many frames :meth:`read` should give (0: unknown, a video that does not say).
        camera: the frames' camera when the input says it (a dataset sequence), else ``None``.
        sequence: the dataset sequence, or ``None``.
    """

    path: Path
    kind: str
    name: str
    size: tuple[int, int]
    frames: int
    camera: Camera | None = None
    sequence: SequenceInfo | None = None
    rate: float | None = None
    fps: float | None = None
    stride: int = 1
    _images: list[Path] | None = None

    def read(self, start: int = 0) -> Iterator[tuple[int, str, float, np.ndarray | None]]:
        """The frames in order: ``(index, FRAME, time in s, uint8 [H,W,3] RGB)``; ``index`` counts the frames
        kept (after ``fps`` / ``stride``), ``FRAME`` names the frame (an image's stem, a video frame's
        6-digit index). Frames before ``start`` come with ``None`` for pixels where that saves decoding."""
        if self._images is not None:
            times = self._times()
            for i, path in enumerate(self._images[:: self.stride]):
                rgb = load_image(path) if i >= start else None
                yield i, path.stem, float(times[i]), rgb
            return
        source = discover_inputs([self.path])[0]
        rate = float(source.rate or FALLBACK_RATE)
        for n, (stem, rgb) in enumerate(read_frames(source, self.fps)):
            if n % self.stride == 0:
                yield n // self.stride, stem, int(stem) / rate, rgb

    def pick(self, indices: set[int]) -> Iterator[tuple[int, np.ndarray]]:
        """The frames ``indices`` (as counted by :meth:`read`) in order: ``(index, uint8 [H,W,3] RGB)``;
        image files are read only for those, a video is decoded up to the last of them."""
        if not indices:
            return
        last = max(indices)
        if self._images is not None:
            for i, path in enumerate(self._images[:: self.stride]):
                if i in indices:
                    yield i, load_image(path)
                if i >= last:
                    return
            return
        for i, _, _, rgb in self.read():
            if i in indices and rgb is not None:
                yield i, rgb
            if i >= last:
                return

    def _times(self) -> np.ndarray:
        """Times of the kept image frames: ``poses.txt``'s timestamps when there are, else the frame index."""
        assert self._images is not None
        seq = self.sequence
        if seq is not None and seq.timestamps is not None:
            return np.asarray(seq.timestamps, dtype=np.float64)[:: self.stride]
        return np.arange(len(self._images), dtype=np.float64)[:: self.stride]

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(times [M], c2w [M,4,4])`` of the kept frames from a sequence's ``poses.txt``, or ``None``."""
        seq = self.sequence
        if seq is None or seq.poses is None or seq.timestamps is None:
            return None
        return seq.timestamps[:: self.stride].copy(), seq.poses[:: self.stride].copy()


def open_ride(path: str | os.PathLike[str], fps: float | None = None, stride: int = 1) -> Ride:
    """Find and check an input (headers only: nothing is decoded).

    Raises:
        CylsfmError: naming the input that is missing, a single image, an empty or mixed-size folder, a
            broken dataset sequence, or a file that is not a video.
        InputError: ``stride`` below 1, ``fps`` not positive or given for images.
    """
    if stride < 1:
        raise InputError(f"stride must be at least 1, got {stride}")
    if fps is not None and not fps > 0:
        raise InputError(f"fps must be a positive number, got {fps}")
    p = Path(path)
    if p.is_dir() and (p / "camera.json").is_file():
        seq = scan_dataset(p)[0]
        ride = Ride(p, "sequence", seq.name, seq.camera.size, len(seq.images[::stride]), seq.camera, seq)
        ride.stride, ride._images = stride, list(seq.images)
    else:
        source = discover_inputs([p])[0]
        if source.kind == "image":
            raise CylsfmError(
                f"{p}: one image has no motion; give a video, a folder of frames or a dataset sequence"
            )
        if len(source.sizes) > 1:
            sizes = ", ".join(f"{w}x{h}" for w, h in source.sizes)
            raise CylsfmError(f"{p}: the frames of a ride must share one size, found {sizes}")
        ride = Ride(p, source.kind, source.name, source.sizes[0], 0, rate=float(source.rate or 0) or None)
        ride.stride = stride
        if source.kind == "folder":
            ride._images = list(source.images)
            ride.frames = len(source.images[::stride])
        else:
            ride.fps = fps
            ride.frames = -(-source.frames // stride) if source.frames and fps is None else 0
    if fps is not None and ride.kind != "video":
        raise InputError(f"{p}: fps thins videos; for frames in a folder or a dataset sequence use stride")
    return ride


def depth_files(dataset: str | os.PathLike[str], ride: Ride) -> list[Path]:
    """The ground-truth depth file of each kept frame of ``ride`` from ``dataset`` (a dataset root or a
    sequence directory), matched by sequence name and frame name.

    Raises:
        CylsfmError: naming what is missing: the sequence, or a frame's depth.
    """
    seqs = scan_dataset(dataset)
    by_name = {s.name: s for s in seqs}
    seq = by_name.get(ride.name) if len(seqs) > 1 else seqs[0]
    if seq is None:
        raise CylsfmError(f"{dataset}: no sequence named {ride.name!r} for the depth of {ride.path}")
    if ride._images is None:
        raise CylsfmError(f"{ride.path}: ground-truth depth needs frames from a folder or a dataset sequence")
    depth = {p.stem: seq.depth_path(i) for i, p in enumerate(seq.images)}
    out = []
    for img in ride._images[:: ride.stride]:
        f = depth.get(img.stem)
        if f is None:
            raise CylsfmError(f"{seq.path}: no ground-truth depth for frame {img.stem}")
        out.append(f)
    return out
