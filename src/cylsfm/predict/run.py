"""Running ``cylsfm predict``: every input's frames through the network, in batches, to files."""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._version import __version__
from ..atomic import atomic_write_text
from ..data.convert import depth_to_camera
from ..data.format import load_depth, save_depth, save_png
from ..data.inputs import InputSource, discover_inputs, expected_frames, read_frames
from ..data.video import FALLBACK_RATE, VideoWriter
from ..errors import InputError
from ..export.colorize import colorize_depth, depth_picture, side_by_side
from ..geometry import Camera, CylindricalCamera, load_camera
from ..model import Predictor
from ..model.checkpoint import checkpoint_id
from ..model.plan import Plan, network_images, network_mask, plan_input
from ..runtime import file_id, fingerprint, progress_bar
from .scale import OdometryFactors, RideScale, network_depth, odometry_factors, ride_scale

__all__ = ["PredictSummary", "RideScale", "predict", "ride_scale"]

log = logging.getLogger(__name__)


#: The settings of the outputs in ``OUT``: a run with the same settings continues where one stopped.
MANIFEST = "predict.json"


@dataclass
class PredictSummary:
    """What :func:`predict` wrote: frames per input name (``resumed``: of them, frames whose files an
    interrupted run with the same settings had written already), and the preview videos."""

    frames: dict[str, int] = field(default_factory=dict)
    videos: list[Path] = field(default_factory=list)
    resumed: int = 0

    @property
    def total(self) -> int:
        return sum(self.frames.values())


def _to_uint8(images: torch.Tensor) -> np.ndarray:
    """``[B,3,H,W]`` in [0, 1] -> ``uint8 [B,H,W,3]``."""
    return (images.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


def _camera_arg(camera: str | os.PathLike[str] | Camera | None) -> tuple[Camera | None, str | None]:
    """The camera of every input and how messages name it."""
    if camera is None:
        return None, None
    if isinstance(camera, Camera):
        return camera, "the given camera"
    return load_camera(camera), str(camera)


def predict(
    checkpoint: str | os.PathLike[str] | Predictor,
    inputs: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    camera: str | os.PathLike[str] | Camera | None = None,
    batch_size: int = 8,
    device: str = "auto",
    amp: bool = True,
    png: bool = True,
    fps: float | None = None,
    progress: bool = True,
    full_resolution: bool = False,
    mask: str | os.PathLike[str] | None = None,
    camera_height: float | None = None,
    odometry: str | os.PathLike[str] | None = None,
) -> PredictSummary:
    """Predict depth for images, image folders and videos; see :mod:`cylsfm.predict` for the outputs.

    Args:
        checkpoint: a checkpoint file, a run directory, or a ready :class:`~cylsfm.model.Predictor`.
        inputs: image files, folders of images and video files.
        out: output directory (created).
        camera: the camera of every input (a ``camera.json`` path or a camera); ``None``: inputs must be
            full cylindrical panoramas of the model's aspect ratio.
        batch_size: frames per network call.
        device: ``auto``, ``cpu``, ``cuda``, ``cuda:N`` (ignored for a ready predictor).
        amp: the networks in bf16 where it is native (:class:`~cylsfm.model.Predictor`); ``False``: fp32.
        png: also write the pictures (input above its coloured depth, at least 1024 wide, a colour scale).
        full_resolution: also write ``FRAME_full.npy`` (and ``FRAME_full.png`` with ``png``), the depth in
            the input's own camera and size (equirectangular input: equirectangular depth, the range).
        fps: take about this many frames a second from videos (and give the preview this rate); ``None``:
            every frame, at the video's own rate.
        progress: show a progress bar on stderr.
        mask: an image of the inputs' aspect ratio, white where they see the scene and black on an occluder
            fixed to the camera (a helmet, a mount): the network sees it filled from the pixels around it,
            and its depth is written as 0 (unknown).
        camera_height: the camera's height above a level ground in metres: every input's depth is written
            in metres, by one factor for the whole input (:func:`ride_scale`); ``None``: network units.
        odometry: the one input's ``cylsfm odometry --refine --depth`` output: every frame's depth in the
            trajectory's scale, brought to its adjusted points (:func:`~.scale.odometry_factors`).

    Every frame of an input is in one scale (never normalised frame by frame), which ``OUT/NAME/scale.json``
    states; its pictures and video preview share one colour range.

    ``OUT/predict.json`` records the settings: the same command after an interruption keeps the frames
    already written (in whole batches) and predicts the rest, as an uninterrupted run would.

    Raises:
        InputError: ``batch_size`` below 1, ``fps`` not positive, an ``odometry`` that does not fit.
        CylsfmError: an input is missing, unreadable or corrupt, or its camera does not suit the model;
            the message names the file. Every input's cameras are checked before anything is written.
    """
    _check_options(batch_size, fps)
    sources = discover_inputs(inputs)
    cam, camera_path = _camera_arg(camera)
    ready = isinstance(checkpoint, Predictor)
    predictor = checkpoint if ready else Predictor.from_checkpoint(checkpoint, device, amp=amp)
    given = _odometry(odometry, checkpoint, predictor, sources, fps, camera_height)
    plan_for = _Plans(predictor, cam, camera_path, Path(mask) if mask is not None else None)
    for source in sources:  # refuse unsuitable inputs (and masks) before writing anything
        for size in source.sizes:
            plan_for.mask(source, size)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    options = {"batch_size": batch_size, "png": png, "full_resolution": full_resolution, "fps": fps}
    options["mask"] = file_id(Path(mask)) if mask is not None else None
    options |= {"camera_height": camera_height, "odometry": given.id if given is not None else None}
    resume = _same_settings(out / MANIFEST, _settings(checkpoint, sources, cam, options))
    total = expected_frames(sources, fps)
    bar = progress_bar(total=total, desc="predict", unit="frame", enabled=progress, leave=True)
    summary = PredictSummary()
    try:
        with torch.inference_mode():
            for source in sources:
                scale = _scale_of(source, plan_for, predictor, fps, camera_height, out, given)
                outputs = _Outputs(png, full_resolution, resume, scale)
                _run_source(source, plan_for, predictor, out, batch_size, outputs, fps, bar, summary)
    finally:
        bar.close()
    return summary


def _check_options(batch_size: int, fps: float | None) -> None:
    if batch_size < 1:
        raise InputError(f"batch_size must be at least 1, got {batch_size}")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")


class _Plans:
    """Each input's :class:`Plan` per frame size (its note printed once), and the mask in its network
    input (``None`` without a mask)."""

    def __init__(
        self, predictor: Predictor, camera: Camera | None, camera_path: str | None, mask: Path | None
    ):
        self.predictor, self.camera, self.camera_path, self.mask_file = predictor, camera, camera_path, mask
        self.vfov_h = predictor.vfov_h
        self.plans: dict[tuple[str, tuple[int, int]], Plan] = {}
        self.masks: dict[tuple[str, tuple[int, int]], torch.Tensor | None] = {}

    def __call__(self, source: InputSource, size: tuple[int, int]) -> Plan:
        key = (source.name, size)
        if key not in self.plans:
            plan = plan_input(source.path, size, self.predictor, self.vfov_h, self.camera, self.camera_path)
            self.plans[key] = plan
            if plan.note:
                log.info("%s: %s", source.path, plan.note)
        return self.plans[key]

    def mask(self, source: InputSource, size: tuple[int, int]) -> torch.Tensor | None:
        key = (source.name, size)
        if key not in self.masks:
            plan = self(source, size)
            self.masks[key] = (
                None
                if self.mask_file is None
                else network_mask(self.mask_file, size, plan, plan.network_input.size)
            )
        return self.masks[key]


def _run_source(
    source: InputSource,
    plan_for: _Plans,
    predictor: Predictor,
    out: Path,
    batch_size: int,
    outputs: _Outputs,
    fps: float | None,
    bar: Any,
    summary: PredictSummary,
) -> None:
    """All frames of one input, ``batch_size`` frames of one size at a time."""
    dest = out / source.name
    dest.mkdir(parents=True, exist_ok=True)
    summary.frames[source.name] = 0
    writer = None
    if source.kind == "video":
        rate = Fraction(fps).limit_denominator(1001) if fps else (source.rate or FALLBACK_RATE)
        writer = VideoWriter(out / f"{source.name}.mp4", rate)
    batch: list[tuple[str, np.ndarray]] = []

    def flush() -> None:
        if batch:
            h, w = batch[0][1].shape[:2]
            plan = plan_for(source, (w, h))
            first = summary.frames[source.name]  # the batch's first frame's index in the input
            if outputs.resume and all(outputs.written(dest, stem) for stem, _ in batch):
                _preview_batch(batch, plan, predictor, dest, writer, outputs.scale.limits)  # (same values)
                summary.resumed += len(batch)
            else:
                seen = plan_for.mask(source, (w, h))
                _run_batch(batch, first, plan, seen, predictor, dest, outputs, writer)
            summary.frames[source.name] += len(batch)
            bar.update(len(batch))
            batch.clear()

    try:
        for stem, rgb in read_frames(source, fps):
            if batch and batch[0][1].shape != rgb.shape:
                flush()
            batch.append((stem, rgb))
            if len(batch) >= batch_size:
                flush()
        flush()
        if writer is not None and writer.close():
            summary.videos.append(writer.path)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise


def _run_batch(
    batch: list[tuple[str, np.ndarray]],
    first: int,
    plan: Plan,
    seen: torch.Tensor | None,
    predictor: Predictor,
    dest: Path,
    outputs: _Outputs,
    writer: VideoWriter | None,
) -> None:
    """Depth of one batch of frames of one size, the input's frames ``first, first + 1, ...``:
    ``DEST/FRAME.npy`` (and the pictures, the full-resolution depth, the video preview)."""
    images = network_images([rgb for _, rgb in batch], plan, predictor.device)
    cam = plan.network_input
    win = predictor.window(cam)
    depth, _ = network_depth(images, plan, seen, predictor)
    factors = [outputs.scale.factor_of(first + i) for i in range(len(batch))]
    depth = depth * np.asarray(factors, dtype=np.float32)[:, None, None]
    shown = _to_uint8(images if win is None else images[..., win[0] : win[1]])
    unit, limits = outputs.scale.unit, outputs.scale.limits
    full = _full_resolution(depth, plan, cam, predictor.fov) if outputs.full else None
    for i, (stem, rgb) in enumerate(batch):
        save_depth(dest / f"{stem}.npy", depth[i])
        if outputs.png:
            save_png(dest / f"{stem}.png", depth_picture(shown[i], depth[i], unit, limits=limits))
        if full is not None:
            save_depth(dest / f"{stem}_full.npy", full[i])
            if outputs.png:
                picture = depth_picture(rgb, full[i], unit, min_width=0, limits=limits)
                save_png(dest / f"{stem}_full.png", picture)
        if writer is not None:
            writer.write(side_by_side([shown[i], colorize_depth(depth[i], *(limits or (None, None)))]))


def _preview_batch(
    batch: list[tuple[str, np.ndarray]],
    plan: Plan,
    predictor: Predictor,
    dest: Path,
    writer: VideoWriter | None,
    limits: tuple[float, float] | None,
) -> None:
    """A batch whose files an interrupted run wrote: only its frames of the video preview, from them."""
    if writer is None:
        return
    images = network_images([rgb for _, rgb in batch], plan, predictor.device)
    win = predictor.window(plan.network_input)
    shown = _to_uint8(images if win is None else images[..., win[0] : win[1]])
    for i, (stem, _) in enumerate(batch):
        depth = load_depth(dest / f"{stem}.npy")
        writer.write(side_by_side([shown[i], colorize_depth(depth, *(limits or (None, None)))]))


def _odometry(
    odometry: Any,
    checkpoint: Any,
    predictor: Predictor,
    sources: list[InputSource],
    fps: float | None,
    camera_height: float | None,
) -> OdometryFactors | None:
    """The per-frame factors of the odometry output given for the one input (``None``: none given),
    checked before anything is written."""
    if odometry is None:
        return None
    if camera_height is not None or len(sources) != 1:
        raise InputError(
            "odometry: give one input, without camera_height (the odometry's output has the ride's scale)"
        )
    ident = checkpoint_id(predictor.models.path if isinstance(checkpoint, Predictor) else checkpoint)
    return odometry_factors(Path(odometry), sources[0], ident, fps)


def _scale_of(
    source: InputSource,
    plans: _Plans,
    predictor: Predictor,
    fps: float | None,
    height: float | None,
    out: Path,
    given: OdometryFactors | None,
) -> RideScale:
    """The input's scale (:func:`ride_scale`, frame by frame with the odometry's factors ``given``),
    said in the log (on the terminal from the command line) and in ``OUT/NAME/scale.json``."""
    scale = ride_scale(source, plans, predictor, fps, height)
    if given is not None:
        scale = given.scale(scale)
    _write_if_changed(out / source.name / "scale.json", json.dumps(scale.to_dict(), indent=1) + "\n")
    log.info("%s: %s", source.name, scale.note)
    return scale


def _write_if_changed(path: Path, text: str) -> None:
    """``text`` into ``path`` unless it holds it already (a continued run leaves its files untouched)."""
    try:
        if path.read_text() == text:
            return
    except OSError:
        pass
    atomic_write_text(path, text)


def _settings(checkpoint: Any, sources: list[InputSource], camera: Camera | None, options: dict) -> dict:
    """What decides the outputs: the checkpoint, the inputs, the camera, the options, the version."""
    return {
        "checkpoint": f"predictor {id(checkpoint)}"
        if isinstance(checkpoint, Predictor)
        else checkpoint_id(checkpoint),
        "inputs": [str(s.path.resolve()) for s in sources],
        "camera": camera.to_dict() if camera is not None else None,
        **options,
        "version": __version__,
    }


def _same_settings(path: Path, settings: dict[str, Any]) -> bool:
    """Whether ``path`` records these settings (then finished frames are kept); records them either way."""
    key = fingerprint(settings)
    try:
        same = json.loads(path.read_text()).get("fingerprint") == key
    except (OSError, ValueError, AttributeError):
        same = False
    atomic_write_text(path, json.dumps({"fingerprint": key, **settings}, indent=1) + "\n")
    return same


@dataclass(frozen=True)
class _Outputs:
    png: bool
    full: bool
    resume: bool
    scale: RideScale

    def written(self, dest: Path, stem: str) -> bool:
        """Whether every file of frame ``stem`` is there (each was written atomically: whole)."""
        names = [f"{stem}.npy"] + [f"{stem}.png"] * self.png
        if self.full:
            names += [f"{stem}_full.npy"] + [f"{stem}_full.png"] * self.png
        return all((dest / n).is_file() for n in names)


def _full_resolution(depth: np.ndarray, plan: Plan, cam: Camera, fov: float) -> np.ndarray:
    """The batch's depth ``[B,h,w]`` in the input's own camera ``[B,H,W]`` (0 where the model does not see);
    ``cam`` is the network's input camera, of which a model trained on crops sees the centred ``fov``."""
    net = cam if fov >= 360 else cam.crop(fov)  # type: ignore[attr-defined]
    assert isinstance(net, CylindricalCamera)
    return depth_to_camera(torch.from_numpy(depth)[:, None], net, plan.camera)[:, 0].numpy()
