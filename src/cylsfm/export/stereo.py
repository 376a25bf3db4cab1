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


def _clip_factor(scenes: list[Scene], options: StereoOptions) -> tuple[float, str]:
    """One depth scale for the whole clip, and its note."""
    if options.camera_height is not None:
        heights = np.array(
            [float(ground_height(torch.from_numpy(s.depth)[None, None], s.camera)[0]) for s in scenes]
        )
        factor, used = metric_scale(heights, options.camera_height)
        return (
            factor,
            f"metres: ground fitted in {used} of {len(scenes)} frames, camera {options.camera_height:g} m",
        )
    known = np.concatenate([s.depth[s.depth > 0] for s in scenes])
    if not len(known):
        raise CylsfmError("the clip's depth has no known pixel")
    factor = options.median_depth / float(np.median(known))
    return factor, f"relative depth: one scale for the clip, median depth {options.median_depth:g}"


def export_stereo_video(
    video: str | os.PathLike[str],
    out: str | os.PathLike[str],
    scene_of: object,
    options: StereoOptions,
    fps: float | None = None,
    progress: bool = True,
) -> tuple[Path, str]:
    """Render every frame of ``video`` in stereo into the video ``out`` (H.264 where available).

    ``scene_of(rgb) -> Scene`` gives a frame's scene (the network's depth). Two passes: the depths first
    (for one scale per clip), then the frames again, rendered. Returns ``(out, the scale's note)``.
    """
    from ..data.inputs import discover_inputs, read_frames
    from ..data.video import FALLBACK_RATE, VideoWriter
    from ..runtime import progress_bar

    options.check()
    (source,) = discover_inputs([video])
    if source.kind != "video":
        raise CylsfmError(f"{video}: not a video")
    scenes = []
    with progress_bar(desc="depth", unit="frame", enabled=progress) as bar:
        for _, rgb in read_frames(source, fps):
            scene = scene_of(rgb)  # type: ignore[operator]
            scenes.append(scene.at_width(options.width) if options.width else scene)
            bar.update(1)
    if not scenes:
        raise CylsfmError(f"{video}: no frames")
    factor, note = _clip_factor(scenes, options)
    rate = Fraction(fps).limit_denominator(1001) if fps else (source.rate or FALLBACK_RATE)
    writer = VideoWriter(Path(out), rate)
    try:
        with progress_bar(total=len(scenes), desc="stereo", unit="frame", enabled=progress) as bar:
            for scene in scenes:
                unit = "metres" if options.camera_height is not None else scene.unit
                pair, _ = _render(scene.scaled(factor, unit, note), options)
                writer.write(pair)
                bar.update(1)
        writer.close()
    except BaseException:
        writer.abort()
        raise
    return Path(out), note
