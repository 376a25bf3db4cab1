"""``cylsfm export stereo``: ODS stereo panoramas (images and videos) for VR headsets and players.

The stereo depends on the depth's scale (the eyes are ``ipd`` apart in the depth's unit). Metric depth (a
depth file, or a network's depth with ``camera_height``) uses it as it is. A network's relative depth is
rescaled so that its median is ``median_depth`` (default 3: a comfortable stereo for street scenes with
a 6.4 cm IPD); for a video one scale is chosen for the whole clip (from the median over all its frames, or
the median of the frames' ground fits), never per frame, so the stereo does not breathe.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import atomic_write_text
from ..data.io import load_depth, load_image, save_depth, save_png
from ..errors import CylsfmError, InputError
from ..geometry import Camera, EquirectangularCamera
from ..geometry.ground import ground_height, metric_scale
from ..runtime import file_id, fingerprint
from .ods import anaglyph, ods_pair, stereo_layout
from .scene import Scene

__all__ = ["StereoOptions", "export_stereo_image", "export_stereo_video"]

#: Frames of a video whose depth one network call predicts.
DEPTH_BATCH = 8


@dataclass(frozen=True)
class StereoOptions:
    """How the stereo is rendered and laid out (see :mod:`cylsfm.export.ods`)."""

    ipd: float = 0.064
    layout: str = "top-bottom"
    equirect: bool = False
    anaglyph: bool = False
    width: int | None = None
    camera_height: float | None = None
    median_depth: float = 3.0

    def check(self) -> None:
        if not self.ipd > 0:
            raise InputError(f"ipd must be a positive distance, got {self.ipd}")
        if self.layout not in ("top-bottom", "side-by-side"):
            raise InputError(f"layout must be top-bottom or side-by-side, got {self.layout!r}")
        if not self.median_depth > 0:
            raise InputError(f"median depth must be positive, got {self.median_depth}")


def _output_camera(scene: Scene, equirect: bool) -> Camera:
    w = scene.camera.width
    return EquirectangularCamera.full(w, w // 2) if equirect else scene.camera


def _scaled(scene: Scene, options: StereoOptions) -> Scene:
    if options.camera_height is not None:
        return scene.to_metres(options.camera_height)
    return scene if scene.metric else scene.normalised(options.median_depth)


def _render(scene: Scene, options: StereoOptions) -> tuple[np.ndarray, np.ndarray | None]:
    left, right = ods_pair(scene, _output_camera(scene, options.equirect), options.ipd)
    return stereo_layout(left, right, options.layout), anaglyph(left, right) if options.anaglyph else None


def export_stereo_image(scene: Scene, out: str | os.PathLike[str], options: StereoOptions) -> list[Path]:
    """Write the stereo pair of one panorama to ``out`` (PNG) and, with ``anaglyph``, ``OUT_anaglyph.png``."""
    options.check()
    if options.width is not None:
        scene = scene.at_width(options.width)
    scene = _scaled(scene, options)
    pair, red_cyan = _render(scene, options)
    out = Path(out)
    save_png(out, pair)
    written = [out]
    if red_cyan is not None:
        written.append(out.with_name(f"{out.stem}_anaglyph.png"))
        save_png(written[-1], red_cyan)
    return written


class _ClipStatistics:
    """What one depth scale for a whole clip needs, gathered frame by frame: a sample of every frame's
    known depths (at most 4096 a frame) and its ground fit."""

    def __init__(self, options: StereoOptions) -> None:
        self.options = options
        self.samples: list[np.ndarray] = []
        self.heights: list[float] = []

    def add(self, scene: Scene) -> None:
        known = scene.depth[scene.depth > 0]
        self.samples.append(known[:: max(1, len(known) // 4096)])
        if self.options.camera_height is not None:
            depth = torch.from_numpy(scene.depth)[None, None]
            self.heights.append(float(ground_height(depth, scene.camera)[0]))

    def factor(self) -> tuple[float, str]:
        """One depth scale for the whole clip, and its note."""
        n = len(self.samples)
        if self.options.camera_height is not None:
            factor, used = metric_scale(np.array(self.heights), self.options.camera_height)
            return (
                factor,
                f"metres: ground fitted in {used} of {n} frames, camera {self.options.camera_height:g} m",
            )
        known = np.concatenate(self.samples) if self.samples else np.zeros(0)
        if not len(known):
            raise CylsfmError("the clip's depth has no known pixel")
        factor = self.options.median_depth / float(np.median(known))
        return factor, f"relative depth: one scale for the clip, median depth {self.options.median_depth:g}"


def _clip_factor(scenes: list[Scene], options: StereoOptions) -> tuple[float, str]:
    """One depth scale for the clip of ``scenes`` (see :class:`_ClipStatistics`)."""
    stats = _ClipStatistics(options)
    for scene in scenes:
        stats.add(scene)
    return stats.factor()


def export_stereo_video(
    video: str | os.PathLike[str],
    out: str | os.PathLike[str],
    scene_of: object,
    options: StereoOptions,
    fps: float | None = None,
    progress: bool = True,
    identity: dict[str, Any] | None = None,
) -> tuple[Path, str]:
    """Render every frame of ``video`` in stereo into the video ``out`` (H.264 where available).

    ``scene_of(rgb, depth=None) -> Scene`` gives a frame's scene (the network's depth; with ``depth``, the
    one it gave before). The work is kept in ``OUT.parts/`` as it goes: every frame's depth (the first
    pass, which also gathers the clip's one scale), then every frame's stereo pair; the video is encoded
    from them at the end and the folder removed. An interrupted export (Ctrl-C, SIGTERM, a full disk)
    leaves the folder, and the same command continues from it: the result equals an uninterrupted run's.
    ``identity``: what else decides the result (the checkpoint, the camera, the mask): parts made with
    other settings are discarded. Returns ``(out, the scale's note)``.
    """
    from ..data.inputs import discover_inputs, read_frames
    from ..data.video import FALLBACK_RATE
    from ..runtime import progress_bar

    options.check()
    (source,) = discover_inputs([video])
    if source.kind != "video":
        raise CylsfmError(f"{video}: not a video")
    out = Path(out)
    parts = _parts(
        out, {"video": file_id(Path(video)), "options": asdict(options), "fps": fps, **(identity or {})}
    )
    stats, stems = _ClipStatistics(options), []
    with progress_bar(desc="depth", unit="frame", enabled=progress) as bar:
        chunk: list[tuple[str, np.ndarray]] = []
        for stem, rgb in read_frames(source, fps):
            chunk.append((stem, rgb))
            if len(chunk) == DEPTH_BATCH:
                stems += _depth_pass(scene_of, chunk, parts / "depth", stats, bar)
                chunk = []
        stems += _depth_pass(scene_of, chunk, parts / "depth", stats, bar)
    if not stems:
        raise CylsfmError(f"{video}: no frames")
    factor, note = stats.factor()
    unit_of = "metres" if options.camera_height is not None else None
    with progress_bar(total=len(stems), desc="stereo", unit="frame", enabled=progress) as bar:
        for stem, rgb in read_frames(source, fps):
            frame = parts / "frames" / f"{stem}.png"
            if not frame.is_file():
                scene = _scene(scene_of, rgb, parts / "depth" / f"{stem}.npy")
                scene = scene.at_width(options.width) if options.width else scene
                save_png(frame, _render(scene.scaled(factor, unit_of or scene.unit, note), options)[0])
            bar.update(1)
    rate = Fraction(fps).limit_denominator(1001) if fps else (source.rate or FALLBACK_RATE)
    _encode(out, rate, [parts / "frames" / f"{stem}.png" for stem in stems])
    shutil.rmtree(parts)
    return out, note


def _depth_pass(
    scene_of: Any, chunk: list[tuple[str, np.ndarray]], folder: Path, stats: _ClipStatistics, bar: Any
) -> list[str]:
    """The first pass over frames ``chunk`` (``(stem, rgb)``): each frame's depth, predicted (in one network
    call when ``scene_of`` has ``many``, as :class:`~cylsfm.export.scene.SceneFunction`) and written once,
    or read back; the clip's statistics gather them in frame order. Returns the chunk's stems."""
    todo = [(stem, rgb) for stem, rgb in chunk if not (folder / f"{stem}.npy").is_file()]
    many = getattr(scene_of, "many", None)
    made: dict[str, Scene] = {}
    if many is not None and len(todo) > 1:
        made = dict(zip([stem for stem, _ in todo], many([rgb for _, rgb in todo]), strict=True))
    for stem, rgb in chunk:
        depth_file = folder / f"{stem}.npy"
        if stem in made:
            scene = made[stem]
            save_depth(depth_file, scene.depth)
        else:
            scene = _scene(scene_of, rgb, depth_file)
        stats.add(scene)
        bar.update(1)
    return [stem for stem, _ in chunk]


def _scene(scene_of: Any, rgb: np.ndarray, depth_file: Path) -> Scene:
    """The frame's scene, its depth kept in ``depth_file`` (predicted and written once)."""
    if depth_file.is_file():
        return scene_of(rgb, depth=load_depth(depth_file))
    scene = scene_of(rgb)
    save_depth(depth_file, scene.depth)
    return scene


def _parts(out: Path, settings: dict[str, Any]) -> Path:
    """``OUT.parts/``: the work of an export of ``out``, kept when its settings are these, else emptied."""
    parts = out.with_name(out.name + ".parts")
    manifest = parts / "settings.json"
    key = fingerprint(settings)
    try:
        same = json.loads(manifest.read_text()).get("fingerprint") == key
    except (OSError, ValueError, AttributeError):
        same = False
    if not same and parts.exists():
        shutil.rmtree(parts)
    for sub in ("depth", "frames"):
        (parts / sub).mkdir(parents=True, exist_ok=True)
    if not same:
        atomic_write_text(manifest, json.dumps({"fingerprint": key, **settings}, default=str) + "\n")
    return parts


def _encode(out: Path, rate: Fraction, frames: list[Path]) -> None:
    """The video ``out`` from the frame images, in order (written aside and moved in place at the end)."""
    from ..data.video import VideoWriter

    writer = VideoWriter(out, rate)
    try:
        for frame in frames:
            writer.write(load_image(frame))
        writer.close()
    except BaseException:
        writer.abort()
        raise
