"""Videos through PyAV: probing a file, decoding its frames (optionally thinned to a frame rate), and
writing the preview MP4 atomically."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CylsfmError

__all__ = [
    "FALLBACK_RATE",
    "VideoWriter",
    "announced_frames",
    "import_av",
    "keep_times",
    "probe_video",
    "video_frames",
]

#: Frame rate assumed (and given to previews) when a video does not tell its own.
FALLBACK_RATE = Fraction(25)


def import_av():
    """The ``av`` module (PyAV), or a :class:`~cylsfm.errors.CylsfmError` saying how to install it."""
    try:
        import av
    except ImportError:
        raise CylsfmError("reading and writing videos needs PyAV (pip install av)") from None
    return av


def probe_video(path: Path) -> tuple[tuple[int, int], int, Fraction | None]:
    """A video's frame size ``(W, H)``, frame count (0: unknown) and average rate (``None``: unknown).

    Reads the container's headers only. Raises :class:`~cylsfm.errors.CylsfmError` naming ``path`` when it
    is not a video PyAV can open.
    """
    av = import_av()
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise CylsfmError(f"{path}: no video stream (not an image or video cylsfm can read)")
            stream = container.streams.video[0]
            size = (int(stream.codec_context.width), int(stream.codec_context.height))
            rate = stream.average_rate or stream.guessed_rate
            frames = int(stream.frames or 0)
    except CylsfmError:
        raise
    except Exception as exc:
        raise CylsfmError(f"{path}: cannot read as an image or a video ({exc})") from None
    if size[0] < 1 or size[1] < 1:
        raise CylsfmError(f"{path}: video stream without a frame size")
    return size, frames, Fraction(rate) if rate else None


def keep_times(fps: float | None) -> Callable[[float], bool]:
    """A predicate on frame times (s) that keeps about ``fps`` frames a second (all when ``None``)."""
    state: dict[str, float] = {}

    def keep(t: float) -> bool:
        if fps is None:
            return True
        nxt = state.get("next")
        if nxt is not None and t < nxt - 1e-6:
            return False
        start = t if nxt is None else nxt
        step = 1.0 / fps
        nxt = start + step
        while nxt <= t + 1e-6:
            nxt += step
        state["next"] = nxt
        return True

    return keep


def video_frames(
    path: Path, rate: Fraction | None, fps: float | None, stats: dict[str, Any] | None = None
) -> Iterator[tuple[str, np.ndarray]]:
    """Decode ``path``: ``(FRAME, uint8 [H,W,3] RGB)`` with ``FRAME`` the 6-digit index in the video.

    ``rate`` (frames per second, :data:`FALLBACK_RATE` when ``None``) times frames without timestamps;
    ``fps`` keeps about that many frames a second (:func:`keep_times`; ``None``: every frame). ``stats``
    (a dict) is kept up to date with ``decoded``, the frames decoded so far (kept or not).
    """
    av = import_av()
    frames_per_second = float(rate or FALLBACK_RATE)
    keep = keep_times(fps)
    try:
        container = av.open(str(path))
    except Exception as exc:
        raise CylsfmError(f"{path}: cannot open video ({exc})") from None
    index = -1
    with container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        decoded = container.decode(stream)
        while True:
            try:
                frame = next(decoded)
            except StopIteration:
                break
            except (av.FFmpegError, OSError, ValueError) as exc:
                raise CylsfmError(f"{path}: cannot decode frame {index + 1} ({exc})") from None
            index += 1
            if stats is not None:
                stats["decoded"] = index + 1
            t = frame.time if frame.time is not None else index / frames_per_second
            if not keep(t):
                continue
            yield f"{index:06d}", frame.to_ndarray(format="rgb24")
    if index < 0:
        raise CylsfmError(f"{path}: the video has no frames that can be decoded")


def announced_frames(path: Path) -> int | None:
    """How many frames a video's container announces: the stream's frame count, else its duration times
    its rate (``None``: it does not say). A video that decodes fewer frames broke off."""
    av = import_av()
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            if stream.frames:
                return int(stream.frames)
            rate = stream.average_rate or stream.guessed_rate
            if stream.duration and stream.time_base and rate:
                return round(float(stream.duration * stream.time_base * rate))
            if container.duration and rate:
                return round(container.duration / 1_000_000 * float(rate))
    except Exception:  # probe_video reported an unreadable file already
        return None
    return None


class VideoWriter:
    """An mp4 written to a temporary name and renamed into place by :meth:`close`.

    Codec: h264 (libx264), or mpeg4 when FFmpeg has no libx264; yuv420p; frames padded with black to even
    sizes.
    """

    def __init__(self, path: Path, rate: Fraction) -> None:
        self.av = import_av()
        self.path = path
        self.rate = rate
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
        self.tmp = Path(tmp)
        self.container = self.av.open(str(self.tmp), mode="w", format="mp4")
        self.stream: Any = None
        self.count = 0

    def _open_stream(self, width: int, height: int) -> None:
        last: Exception | None = None
        for codec in ("libx264", "mpeg4"):
            try:
                stream = self.container.add_stream(codec, rate=self.rate)
            except Exception as exc:  # unknown encoder in this FFmpeg build
                last = exc
                continue
            stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
            if codec == "libx264":
                stream.options = {"crf": "20", "preset": "fast"}
            else:
                stream.bit_rate = max(1_000_000, int(width * height * float(self.rate) * 0.3))
            self.stream = stream
            return
        raise CylsfmError(f"{self.path}: FFmpeg has neither an h264 nor an mpeg4 encoder ({last})")

    def write(self, rgb: np.ndarray) -> None:
        """Append a ``uint8 [H,W,3]`` RGB frame (every frame must have the first one's size)."""
        h, w = rgb.shape[:2]
        ph, pw = h + h % 2, w + w % 2
        if (ph, pw) != (h, w):
            rgb = np.pad(rgb, ((0, ph - h), (0, pw - w), (0, 0)))
        if self.stream is None:
            self._open_stream(pw, ph)
        elif (pw, ph) != (self.stream.width, self.stream.height):
            raise CylsfmError(f"{self.path}: frame size changed within the video")
        frame = self.av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame.pts = self.count
        frame.time_base = 1 / self.rate
        for packet in self.stream.encode(frame):
            self.container.mux(packet)
        self.count += 1

    def close(self) -> bool:
        """Finish the file and move it into place; ``False`` (and nothing written) without frames."""
        if self.stream is None:
            self.abort()
            return False
        try:
            for packet in self.stream.encode(None):
                self.container.mux(packet)
            self.container.close()
            os.replace(self.tmp, self.path)
        except BaseException:
            self.abort()
            raise
        return True

    def abort(self) -> None:
        """Drop the temporary file; an earlier ``path`` stays as it was."""
        try:
            self.container.close()
        except Exception:  # closing a half-written container may fail; the file goes anyway
            pass
        self.tmp.unlink(missing_ok=True)
