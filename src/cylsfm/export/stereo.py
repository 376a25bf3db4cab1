"""``cylsfm export stereo``: ODS stereo panoramas (images and videos) for VR headsets and players.

The stereo depends on the depth's scale (the eyes are ``ipd`` apart in the depth's unit). Metric depth (a
depth file, or a network's depth with ``camera_height``) uses it as it is. A network's relative depth is
rescaled so that its median is ``median_depth`` (default 3: a comfortable stereo for street scenes with
a 6.4 cm IPD); for a video one scale is chosen for the whole clip (from the median over all its frames, or
the median of the frames' ground fits), never per frame, so the stereo does not breathe.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from ..data.io import save_png
from ..errors import CylsfmError, InputError
from ..geometry import Camera, EquirectangularCamera
from ..geometry.ground import ground_height, metric_scale
from .ods import anaglyph, ods_pair, stereo_layout
from .scene import Scene

__all__ = ["StereoOptions", "export_stereo_image", "export_stereo_video"]


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
) -> tuple[Path, str]:
    """Render every frame of ``video`` in stereo into the video ``out`` (H.264 where available).

    ``scene_of(rgb) -> Scene`` gives a frame's scene (the network's depth). Two passes over the video: the
    first predicts every frame's depth for the clip's one scale (keeping only a sample of it), the
    second decodes and predicts again and renders (so that no clip is held in memory). Returns ``(out,
    the scale's note)``.
    """
    from ..data.inputs import discover_inputs, read_frames
    from ..data.video import FALLBACK_RATE, VideoWriter
    from ..runtime import progress_bar

    options.check()
    (source,) = discover_inputs([video])
    if source.kind != "video":
        raise CylsfmError(f"{video}: not a video")
    stats = _ClipStatistics(options)
    with progress_bar(desc="depth", unit="frame", enabled=progress) as bar:
        for _, rgb in read_frames(source, fps):
            stats.add(scene_of(rgb))  # type: ignore[operator]
            bar.update(1)
    if not stats.samples:
        raise CylsfmError(f"{video}: no frames")
    factor, note = stats.factor()
    unit_of = "metres" if options.camera_height is not None else None
    rate = Fraction(fps).limit_denominator(1001) if fps else (source.rate or FALLBACK_RATE)
    writer = VideoWriter(Path(out), rate)
    try:
        with progress_bar(total=len(stats.samples), desc="stereo", unit="frame", enabled=progress) as bar:
            for _, rgb in read_frames(source, fps):
                scene = scene_of(rgb)  # type: ignore[operator]
                scene = scene.at_width(options.width) if options.width else scene
                pair, _ = _render(scene.scaled(factor, unit_of or scene.unit, note), options)
                writer.write(pair)
                bar.update(1)
        writer.close()
    except BaseException:
        writer.abort()
        raise
    return Path(out), note
