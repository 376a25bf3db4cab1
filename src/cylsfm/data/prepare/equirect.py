"""``cylsfm prepare equirect`` and ``cylsfm prepare frames``: 360-degree footage as dataset sequences.

Each input (a video file or a folder of images) becomes one sequence ``OUT/NAME``. Equirectangular frames
(2:1, the whole sphere) are resampled into the cylinder of the output camera by a map computed once per
input (:class:`~cylsfm.data.convert.Resampler`: supersampled and area-averaged, so shrinking a 3840x1920
frame to 512x128 does not alias). Frames keep their source's name: a video frame's 6-digit index in the
video, an image's file stem, so that a second run skips what the first wrote
(:class:`~cylsfm.data.prepare.sequence.PreparedSequence`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from ..._version import __version__
from ...errors import CylsfmError, InputError
from ...geometry import Camera, CylindricalCamera, EquirectangularCamera
from ...runtime import progress_bar
from ..convert import Resampler
from ..inputs import InputSource, discover_inputs
from ..io import load_image, load_mask
from ..video import FALLBACK_RATE, announced_frames, video_frames
from .sequence import PreparedSequence

__all__ = ["EquirectOptions", "PrepareReport", "prepare_equirect", "prepare_frames"]

#: Width of the grey thumbnails compared to drop frames of a camera standing still.
_THUMB_WIDTH = 64


@dataclass(frozen=True)
class EquirectOptions:
    """How footage is prepared.

    Attributes:
        size: the output panoramas' ``(W, H)``.
        vfov_h: the output cylinder's rows span ``h`` in ``[-vfov_h, vfov_h]`` (1: +-45 degrees of
            elevation, the paper's Headcam band).
        camera: the output camera exactly (overrides ``size`` and ``vfov_h``), e.g. an existing dataset's.
        fps: take about this many frames a second from videos (``None``: all; the paper: 5).
        start, end: keep the frames from ``start`` to ``end``: seconds into a video, positions (0-based)
            in a folder of images.
        mask: a mask image (white: use) of the mount or helmet, in equirectangular (2:1) or in the
            output's cylindrical coordinates (the output's size); written as each sequence's ``mask.png``.
        exclude: frame names to leave out (a video frame's 6-digit index, an image's stem).
        exclude_positions: frames to leave out by their position among the frames taken (0-based: the
            k-th frame kept by ``fps`` from a video, the k-th image of a folder), as frame lists written
            against ``ffmpeg -vf fps=N`` output number them (minus one for ffmpeg's 1-based file names).
        drop_static: leave out a frame whose grey thumbnail differs from the last kept one's by less than
            this mean absolute difference (in [0, 1]; 0: keep every frame).
        batch: frames converted at once.
    """

    size: tuple[int, int] = (512, 128)
    vfov_h: float = 1.0
    camera: CylindricalCamera | None = None
    fps: float | None = None
    start: float | None = None
    end: float | None = None
    mask: Path | None = None
    exclude: frozenset[str] = field(default_factory=frozenset)
    exclude_positions: frozenset[int] = field(default_factory=frozenset)
    drop_static: float = 0.0
    batch: int = 8

    def output_camera(self) -> CylindricalCamera:
        if self.camera is not None:
            return self.camera
        return CylindricalCamera.full(int(self.size[0]), int(self.size[1]), float(self.vfov_h))

    def settings(self) -> dict[str, Any]:
        """What decides the output (for :class:`PreparedSequence`)."""
        mask = None
        if self.mask is not None:
            st = Path(self.mask).stat()
            mask = [str(Path(self.mask).resolve()), st.st_size, st.st_mtime_ns]
        return {
            "camera": self.output_camera().to_dict(),
            "fps": self.fps,
            "start": self.start,
            "end": self.end,
            "mask": mask,
            "exclude": sorted(self.exclude),
            "drop_static": self.drop_static,
            **({"exclude_positions": sorted(self.exclude_positions)} if self.exclude_positions else {}),
        }


@dataclass
class PrepareReport:
    """What :func:`prepare_equirect` did with one input."""

    source: Path
    sequence: Path
    written: int = 0
    skipped: bool = False
    decoded: int | None = None
    announced: int | None = None
    broke_off: str | None = None
    dropped_static: int = 0

    def line(self) -> str:
        """One line for the user."""
        if self.skipped:
            return f"{self.sequence}: already prepared"
        text = f"{self.sequence}: {self.written} frames"
        if self.decoded is not None:
            of = f" of {self.announced}" if self.announced else ""
            text += f" (read {self.decoded}{of} frames of {self.source}"
            text += f"; the video breaks off: {self.broke_off})" if self.broke_off else ")"
        if self.dropped_static:
            text += f"; {self.dropped_static} dropped as standing still"
        return text


def _check_options(options: EquirectOptions) -> None:
    w, h = options.size
    if options.camera is None and (w < 8 or h < 8):
        raise InputError(f"size must be at least 8x8, got {w}x{h}")
    if options.camera is not None and not isinstance(options.camera, CylindricalCamera):
        raise InputError(f"the output camera must be cylindrical, got {options.camera.model}")
    if not (options.vfov_h > 0 and math.isfinite(options.vfov_h)):
        raise InputError(f"vfov_h must be a positive number, got {options.vfov_h}")
    if options.fps is not None and not options.fps > 0:
        raise InputError(f"fps must be a positive number, got {options.fps}")
    if options.start is not None and options.end is not None and options.end < options.start:
        raise InputError(f"end ({options.end}) is before start ({options.start})")
    if not 0 <= options.drop_static < 1:
        raise InputError(f"drop_static must be in [0, 1), got {options.drop_static}")
    if options.batch < 1:
        raise InputError(f"batch must be at least 1, got {options.batch}")


def _equirect_camera(source: InputSource) -> EquirectangularCamera:
    if len(source.sizes) > 1:
        sizes = ", ".join(f"{w}x{h}" for w, h in source.sizes)
        raise CylsfmError(f"{source.path}: the frames of one input must share one size, found {sizes}")
    w, h = source.sizes[0]
    if abs(w - 2 * h) > 1:
        raise CylsfmError(
            f"{source.path}: {w}x{h} is not an equirectangular 360-degree panorama (width must be twice the "
            "height); for panoramas already cylindrical use `cylsfm prepare frames`"
        )
    return EquirectangularCamera.full(w, h)


def _output_mask(path: Path, camera: CylindricalCamera) -> np.ndarray:
    """The mask file in the output's coordinates: ``bool [H,W]``."""
    with Image.open(path) as im:
        mw, mh = im.size
    if (mw, mh) == camera.size:
        return load_mask(path) > 0.5
    if abs(mw - 2 * mh) > 1:
        raise CylsfmError(
            f"{path}: a mask must be equirectangular (2:1) or the output's size {camera.width}x{camera.height}, "
            f"got {mw}x{mh}"
        )
    grey = torch.from_numpy(load_mask(path))[None, None]
    return (Resampler(EquirectangularCamera.full(mw, mh), camera)(grey)[0, 0] >= 0.5).numpy()


def _thumb(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    tw = min(_THUMB_WIDTH, w)
    th = max(1, round(h * tw / w))
    im = Image.fromarray(image).convert("L").resize((tw, th), Image.Resampling.BOX)
    return np.asarray(im, dtype=np.float32) / 255.0


class _Frames:
    """An input's frames in order as ``(name, time or position, uint8 RGB)``, recording how many a video
    decoded and where it broke off."""

    def __init__(
        self, source: InputSource, options: EquirectOptions, wanted: Callable[[str, float, int], bool]
    ) -> None:
        self.source = source
        self.options = options
        self.wanted = wanted
        self.stats: dict[str, Any] = {}
        self.broke_off: str | None = None

    def __iter__(self) -> Iterator[tuple[str, float, np.ndarray | None]]:
        """Images of a folder are decoded only where ``wanted(name, position)``; ``None`` elsewhere."""
        src = self.source
        if src.kind != "video":
            for i, path in enumerate(src.images):
                yield path.stem, float(i), load_image(path) if self.wanted(path.stem, float(i), i) else None
            return
        rate = float(src.rate or FALLBACK_RATE)
        frames = video_frames(src.path, src.rate, self.options.fps, self.stats)
        while True:
            try:
                stem, rgb = next(frames)
            except StopIteration:
                return
            except CylsfmError as exc:
                if not self.stats.get("decoded"):
                    raise
                self.broke_off = str(exc)
                return
            yield stem, int(stem) / rate, rgb


def _in_range(t: float, options: EquirectOptions) -> bool:
    return options.start is None or t >= options.start - 1e-9


def _past_end(t: float, options: EquirectOptions) -> bool:
    return options.end is not None and t > options.end + 1e-9


class _Converter:
    """Batches of frames through the resampler (or as they are), dropping a still camera's frames."""

    def __init__(self, seq: PreparedSequence, resample: Resampler | None, options: EquirectOptions) -> None:
        self.seq, self.resample, self.options = seq, resample, options
        self.pending: list[tuple[str, np.ndarray]] = []
        self.dropped = 0
        last = seq.last_frame() if options.drop_static else None
        self.last_thumb = _thumb(load_image(last)) if last is not None else None

    def add(self, name: str, rgb: np.ndarray) -> None:
        self.pending.append((name, rgb))
        if len(self.pending) >= self.options.batch:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        names = [n for n, _ in self.pending]
        frames = [rgb for _, rgb in self.pending]
        out = frames if self.resample is None else self.resample.frames(frames)
        self.pending.clear()
        for name, image in zip(names, out, strict=True):
            if self.options.drop_static:
                thumb = _thumb(image)
                still = (
                    self.last_thumb is not None
                    and float(np.abs(thumb - self.last_thumb).mean()) < self.options.drop_static
                )
                if still:
                    self.dropped += 1
                    continue
                self.last_thumb = thumb
            self.seq.add(name, np.ascontiguousarray(image))


def _prepare_one(
    source: InputSource,
    out: Path,
    options: EquirectOptions,
    overwrite: bool,
    bar: Any,
    equirect: bool,
) -> PrepareReport:
    camera = options.output_camera()
    if equirect:
        src_camera: Camera = _equirect_camera(source)
        resample: Resampler | None = Resampler(src_camera, camera)
    else:
        if source.sizes != [camera.size]:
            sizes = ", ".join(f"{w}x{h}" for w, h in source.sizes)
            raise CylsfmError(
                f"{source.path}: frames are {sizes} but the camera is {camera.width}x{camera.height}"
            )
        resample = None
    settings = {
        "source": str(source.path.resolve()),
        "kind": source.kind,
        "equirect": equirect,
        **options.settings(),
    }
    seq = PreparedSequence(out / source.name, camera, settings, overwrite)
    report = PrepareReport(source.path, seq.path)
    if seq.finished:
        report.skipped, report.written = True, len(seq.done)
        return report
    mask = _output_mask(Path(options.mask), camera) if options.mask is not None else None

    def wanted(name: str, t: float, position: int) -> bool:
        if position in options.exclude_positions or name in options.exclude:
            return False
        return _in_range(t, options) and not seq.has(name)

    frames = _Frames(source, options, wanted)
    convert = _Converter(seq, resample, options)
    try:
        for position, (name, t, rgb) in enumerate(frames):
            bar.update(1)
            if _past_end(t, options):
                break
            if rgb is not None and wanted(name, t, position):
                convert.add(name, rgb)
        convert.flush()
    finally:
        seq.wait()  # frames handed to the writers are on disk (also when interrupted)
    report.written, report.dropped_static = len(seq.done), convert.dropped
    if source.kind == "video":
        report.decoded = int(frames.stats.get("decoded", 0))
        report.announced = announced_frames(source.path)
        report.broke_off = frames.broke_off
        short = report.announced is not None and report.decoded < report.announced - 1 and options.end is None
        if short and report.broke_off is None:
            report.broke_off = f"decoding stopped after frame {report.decoded - 1}"
    seq.note(
        cylsfm=__version__,
        frames_decoded=report.decoded,
        frames_announced=report.announced,
        broke_off=report.broke_off,
        dropped_static=report.dropped_static,
    )
    seq.finish(mask)
    return report


def _prepare(
    inputs: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    options: EquirectOptions,
    overwrite: bool,
    progress: bool,
    equirect: bool,
) -> list[PrepareReport]:
    _check_options(options)
    sources = discover_inputs(inputs)
    for s in sources:
        if s.kind == "image":
            raise CylsfmError(f"{s.path}: one image is not a sequence; give a video or a folder of frames")
        if equirect:
            _equirect_camera(s)  # every input checked before anything is written
    if options.mask is not None and not Path(options.mask).is_file():
        raise CylsfmError(f"{options.mask}: mask file not found")
    dest = Path(out)
    dest.mkdir(parents=True, exist_ok=True)
    reports = []
    for s in sources:
        total = (s.frames or None) if s.kind != "video" or options.fps is None else None
        with progress_bar(total=total, desc=s.name, unit="frame", enabled=progress) as bar:
            reports.append(_prepare_one(s, dest, options, overwrite, bar, equirect))
    return reports


def prepare_equirect(
    inputs: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    options: EquirectOptions | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> list[PrepareReport]:
    """Convert equirectangular videos and image folders into cylindrical dataset sequences ``OUT/NAME``.

    Args:
        inputs: video files and folders of equirectangular (2:1) images; one sequence each.
        out: the dataset root (created).
        options: :class:`EquirectOptions` (defaults: 512x128, +-45 degrees, every frame).
        overwrite: start each sequence again instead of continuing or skipping it.
        progress: show a progress bar.

    Returns:
        One :class:`PrepareReport` per input.

    Raises:
        CylsfmError: naming the input or file: not found, not 2:1, a single image, mixed sizes, a video that
            cannot be decoded at all, a sequence prepared with other settings, a bad mask.
    """
    return _prepare(inputs, out, options or EquirectOptions(), overwrite, progress, equirect=True)


def prepare_frames(
    inputs: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    camera: CylindricalCamera,
    options: EquirectOptions | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> list[PrepareReport]:
    """Folders (or videos) of cylindrical panoramas already warped, of ``camera``'s size, as sequences.

    The frames are written as they are (PNG); ``options`` other than ``camera`` select and drop frames as
    for :func:`prepare_equirect`.
    """
    base = options or EquirectOptions()
    opts = EquirectOptions(**{**base.__dict__, "camera": camera})
    return _prepare(inputs, out, opts, overwrite, progress, equirect=False)
