"""The inputs of ``cylsfm predict`` and ``cylsfm odometry``: classifying paths as images, folders or videos, naming their outputs,
and reading their frames."""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from ..errors import CylsfmError
from .format import image_size, load_image
from .video import probe_video, video_frames

__all__ = ["IMAGE_FILE_SUFFIXES", "InputSource", "discover_inputs", "expected_frames", "read_frames"]

#: File suffixes (lower case) read as images; any other file is tried as a video.
IMAGE_FILE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


@dataclass
class InputSource:
    """One input of ``cylsfm predict``.

    Attributes:
        path: the file or folder given.
        kind: ``"image"``, ``"folder"`` or ``"video"``.
        name: output name (``OUT/name/``, ``OUT/name.mp4``), unique among the inputs.
        sizes: the distinct frame sizes ``(W, H)`` (from file headers / the video stream).
        images: the image files of an image or folder input, in order.
        frames: the number of frames (videos: the container's count, 0 when unknown).
        rate: a video's average frame rate (frames per second), ``None`` when unknown.
    """

    path: Path
    kind: str
    name: str
    sizes: list[tuple[int, int]]
    images: list[Path] = field(default_factory=list)
    frames: int = 0
    rate: Fraction | None = None


def _folder_images(folder: Path) -> list[Path]:
    files = sorted(
        (
            p
            for p in folder.iterdir()
            if not p.name.startswith(".") and p.suffix.lower() in IMAGE_FILE_SUFFIXES
        ),
        key=lambda p: p.name,
    )
    if not files:
        raise CylsfmError(f"{folder}: no images in the folder (expected {', '.join(IMAGE_FILE_SUFFIXES)})")
    stems: dict[str, Path] = {}
    for p in files:
        if p.stem in stems:
            raise CylsfmError(f"{p}: two images named {p.stem!r} ({stems[p.stem].name} and {p.name})")
        stems[p.stem] = p
    return files


def _unique(base: str, used: set[str]) -> str:
    """``base``, or ``base-2``, ``base-3`` ... the first not in ``used`` (which it joins)."""
    name, n = base, 1
    while name in used:
        n += 1
        name = f"{base}-{n}"
    used.add(name)
    return name


def discover_inputs(paths: Sequence[str | os.PathLike[str]]) -> list[InputSource]:
    """Classify and probe the inputs (file headers only; no pixel is decoded).

    Raises:
        CylsfmError: naming the input that does not exist, is an empty folder, or is neither a readable
            image nor a video PyAV can open.
    """
    if not paths:
        raise CylsfmError("no inputs given")
    out: list[InputSource] = []
    used: set[str] = set()
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise CylsfmError(f"{path}: input not found")
        if path.is_dir():
            images = _folder_images(path)
            kind, base = "folder", path.resolve().name or "input"
        elif path.suffix.lower() in IMAGE_FILE_SUFFIXES:
            images = [path]
            kind, base = "image", path.stem
        else:
            images, kind, base = [], "video", path.stem
        name = _unique(base, used)
        if kind == "video":
            size, frames, rate = probe_video(path)
            out.append(InputSource(path, kind, name, [size], frames=frames, rate=rate))
        else:
            sizes: list[tuple[int, int]] = []
            for img in images:
                s = image_size(img)  # DatasetError names the file
                if s not in sizes:
                    sizes.append(s)
            out.append(InputSource(path, kind, name, sizes, images=images, frames=len(images)))
    return out


def read_frames(source: InputSource, fps: float | None) -> Iterator[tuple[str, np.ndarray]]:
    """The frames of an input, in order: ``(FRAME, uint8 [H,W,3] RGB)``.

    ``FRAME`` is an image's file stem, or a video frame's 6-digit index in the video; ``fps`` thins videos
    to about that many frames a second (``None``: every frame).
    """
    if source.kind == "video":
        yield from video_frames(source.path, source.rate, fps)
        return
    for path in source.images:
        yield path.stem, load_image(path)  # DatasetError (a CylsfmError) names a corrupt file


def expected_frames(sources: Sequence[InputSource], fps: float | None) -> int | None:
    """How many frames :func:`read_frames` will give in all (``None`` when a video does not say)."""
    import math

    total: int | None = 0
    for s in sources:
        if s.kind == "video" and fps is not None and s.rate:
            n = math.ceil(s.frames * min(1.0, fps / float(s.rate)))
        else:
            n = s.frames
        total = None if (total is None or not n) else total + n
    return total
