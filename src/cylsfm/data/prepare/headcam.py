"""``cylsfm prepare headcam``: the paper's Headcam dataset (helmet-mounted Samsung Gear 360 rides, one
lossless H.264 ``.mkv`` equirectangular video per recording day) prepared as the paper did.

Defaults as published: frames taken at 5 fps (for a 30 fps video every 6th frame from the first, the
frames ``ffmpeg -vf fps=5`` extracts), warped to the cylinder ``h`` in ``[-1, 1]`` (+-45 degrees) and
area-averaged to 512x128 (or ``--size 2048x512``), a helmet mask when given, frames of an excluded-frames
list left out, a 90/10 train/validation split by frame.

The excluded-frames list holds one frame a line as ``VIDEO NUMBER`` or ``VIDEO/NUMBER`` (``VIDEO``: the
video's file name without extension, e.g. the recording day; a bare ``NUMBER`` when ``ROOT`` holds one
video). ``NUMBER`` counts the 5 fps frames. The original code counted them from 0 while ``ffmpeg``'s
``%05d`` file names count from 1: ``exclude_numbering`` says which the list uses (default 0), so that the
right frame is left out rather than its neighbour.
"""

from __future__ import annotations

import os
import re
from dataclasses import replace
from pathlib import Path

from ...errors import CylsfmError
from ..io import read_text
from .equirect import EquirectOptions, PrepareReport, prepare_equirect

__all__ = ["HEADCAM_FPS", "VIDEO_SUFFIXES", "prepare_headcam", "read_excluded"]

HEADCAM_FPS = 5.0
VIDEO_SUFFIXES = (".mkv", ".mp4", ".mov", ".avi", ".webm")
_LINE = re.compile(r"^(?:(?P<video>[^\s/]+)[\s/]+)?(?P<number>\d+)(?:\.\w+)?$")


def read_excluded(
    path: str | os.PathLike[str], videos: list[str], numbering: int
) -> dict[str, frozenset[int]]:
    """The excluded-frames list as ``{video stem: positions (0-based)}``.

    Raises:
        CylsfmError: naming the file and line: a line that is not ``[VIDEO] NUMBER``, an unknown video, a
            bare number with several videos, a number below ``numbering``.
    """
    out: dict[str, set[int]] = {v: set() for v in videos}
    for lineno, raw in enumerate(read_text(path, "excluded-frames list").splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        m = _LINE.match(line)
        if m is None:
            raise CylsfmError(f"{path}:{lineno}: expected 'VIDEO NUMBER' or 'NUMBER', got {line!r}")
        video = m.group("video")
        if video is None:
            if len(videos) != 1:
                raise CylsfmError(
                    f"{path}:{lineno}: name the video of frame {line} (one of {', '.join(videos)})"
                )
            video = videos[0]
        if video not in out:
            raise CylsfmError(f"{path}:{lineno}: no video {video!r} (found {', '.join(videos)})")
        number = int(m.group("number")) - numbering
        if number < 0:
            raise CylsfmError(f"{path}:{lineno}: frame numbers start at {numbering}, got {m.group('number')}")
        out[video].add(number)
    return {v: frozenset(s) for v, s in out.items()}


def prepare_headcam(
    root: str | os.PathLike[str],
    out: str | os.PathLike[str],
    options: EquirectOptions | None = None,
    exclude_list: str | os.PathLike[str] | None = None,
    exclude_numbering: int = 0,
    overwrite: bool = False,
    progress: bool = True,
) -> list[PrepareReport]:
    """Prepare every video in ``root`` (one sequence each, named by the file) as the paper did.

    ``options`` default to 5 fps, 512x128, ``h`` in ``[-1, 1]``.

    Raises:
        CylsfmError: ``root`` missing or without videos, a bad excluded-frames list, and everything
            :func:`~cylsfm.data.prepare.prepare_equirect` raises.
    """
    options = options or EquirectOptions(fps=HEADCAM_FPS)
    if exclude_numbering not in (0, 1):
        raise CylsfmError(f"exclude_numbering must be 0 or 1, got {exclude_numbering}")
    folder = Path(root)
    if not folder.is_dir():
        raise CylsfmError(f"{folder}: folder not found")
    videos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    if not videos:
        raise CylsfmError(f"{folder}: no videos ({', '.join(VIDEO_SUFFIXES)}) found")
    stems = [p.stem for p in videos]
    excluded = read_excluded(exclude_list, stems, exclude_numbering) if exclude_list is not None else {}
    reports = []
    for video in videos:
        opts = replace(options, exclude_positions=excluded.get(video.stem, frozenset()))
        reports.extend(prepare_equirect([video], out, opts, overwrite, progress))
    return reports
