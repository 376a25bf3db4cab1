"""Depth maps for images, image folders and videos with a trained checkpoint (``cylsfm predict``).

Inputs are image files (png, jpg ...), folders (every image directly inside, sorted by name) and videos
(anything PyAV decodes: mp4, mkv, mov, webm ...). For an input named ``NAME`` (its file stem or folder
name; a second input of the same name becomes ``NAME-2``) the outputs are::

    OUT/NAME/FRAME.npy   float32 [H,W] depth in the network's (unknown) scale, > 0
    OUT/NAME/FRAME.png   the depth coloured by inverse depth (near = bright; cylsfm.export.colorize)
    OUT/NAME.mp4         videos only: input frame above its coloured depth (h264, or mpeg4 without libx264)

``FRAME`` is an image's file stem, or a video frame's 6-digit index in the video (counted before ``fps``
subsampling). Every file is written atomically (a temporary file, then ``os.replace``), so an interrupted or
failed run leaves complete files only; frames already written stay.

Cameras. The networks expect the panoramas they were trained on: full 360-degree cylindrical panoramas
whose rows span ``h`` in ``[-vfov_h, vfov_h]`` (:func:`model_vfov_h`) with the training aspect ratio.

* Without a camera file, an input must have that aspect ratio (width/height within 2%); it is taken as
  ``CylindricalCamera.full(w, h, vfov_h)`` and its depth comes back at its own resolution.
* With a camera file (``camera.json``, see ``cylsfm camera``): a full cylindrical panorama of the training
  vertical field of view is used as it is; an equirectangular 360-degree image (or a full cylindrical one of
  another vertical field of view) is first resampled (:func:`cylsfm.data.convert.to_cylinder`) into the
  model's cylinder at the network's input size, and its depth (and the video preview) is at that size.
  Partial panoramas and pinhole cameras are refused: a panoramic model has never seen them.

For a model trained on centred crops (``data.fov < 360``) the inputs are still full panoramas; the depth
covers the crop the network sees.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .data.convert import to_cylinder
from .data.format import image_size, load_image, save_depth, save_png
from .errors import CylsfmError
from .export.colorize import colorize_depth, side_by_side
from .geometry import Camera, CylindricalCamera, EquirectangularCamera, PinholeCamera, load_camera
from .model import Predictor

__all__ = [
    "ASPECT_TOLERANCE",
    "IMAGE_FILE_SUFFIXES",
    "InputSource",
    "PredictSummary",
    "discover_inputs",
    "model_camera",
    "model_vfov_h",
    "predict",
]

#: File suffixes (lower case) read as images; any other file is tried as a video.
IMAGE_FILE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
#: Relative tolerance on the aspect ratio (and vertical field of view) matching the model's.
ASPECT_TOLERANCE = 0.02
#: Vertical half-extent ``vfov_h`` of the training panoramas when the training data does not say otherwise.
DEFAULT_VFOV_H = 1.0
#: Output frame rate of previews when the video does not tell its own.
_FALLBACK_RATE = Fraction(25)


# --------------------------------------------------------------------------------------------- model
def model_vfov_h(config: Any) -> float:
    """The vertical extent ``vfov_h`` (rows span ``h`` in ``[-vfov_h, vfov_h]``) the model was trained on.

    Recorded in the configuration when training starts (``config.data.vfov_h``); for older configurations
    read from the training dataset's ``camera.json`` (``height / (2 fy)``) when ``config.data.root`` is still
    there and holds a cylindrical camera; otherwise :data:`DEFAULT_VFOV_H` (1.0, +-45 degrees: the
    cameras of ``cylsfm synth`` and of the paper's preparation). Checkpoints store no camera.
    """
    recorded = getattr(getattr(config, "data", None), "vfov_h", None)
    if recorded:
        return float(recorded)
    root = getattr(getattr(config, "data", None), "root", "") or ""
    if root:
        try:
            from .data.format import find_sequence_dirs

            cam = load_camera(find_sequence_dirs(root)[0] / "camera.json")
            if isinstance(cam, CylindricalCamera) and cam.wraps:
                return float(cam.height) / (2.0 * float(cam.fy))
        except (CylsfmError, OSError):
            pass
    return DEFAULT_VFOV_H


def _full_width(predictor: Predictor) -> int:
    """Width of the full panorama whose centred ``fov`` crop is the network's input width."""
    return predictor.size[0]  # config.data.width is the panorama's width; the crop comes after it


def model_camera(predictor: Predictor, vfov_h: float | None = None) -> CylindricalCamera:
    """The full 360-degree cylinder the model expects, at the network's input size.

    ``CylindricalCamera.full(W, H, vfov_h)`` with ``(W, H)`` the network's input size (for a model trained
    on ``fov``-degree crops, ``W`` is the full turn around them). ``vfov_h`` defaults to
    :func:`model_vfov_h` of the checkpoint's configuration.
    """
    if vfov_h is None:
        vfov_h = model_vfov_h(predictor.config)
    return CylindricalCamera.full(_full_width(predictor), predictor.size[1], vfov_h)


def _aspect_ok(a: float, b: float) -> bool:
    return abs(a / b - 1.0) <= ASPECT_TOLERANCE


# --------------------------------------------------------------------------------------------- inputs
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


def _import_av():
    try:
        import av
    except ImportError:
        raise CylsfmError("reading and writing videos needs PyAV (pip install av)") from None
    return av


def _probe_video(path: Path) -> tuple[tuple[int, int], int, Fraction | None]:
    av = _import_av()
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
        name, n = base, 1
        while name in used:
            n += 1
            name = f"{base}-{n}"
        used.add(name)
        if kind == "video":
            size, frames, rate = _probe_video(path)
            out.append(InputSource(path, kind, name, [size], frames=frames, rate=rate))
        else:
            sizes: list[tuple[int, int]] = []
            for img in images:
                s = image_size(img)  # DatasetError names the file
                if s not in sizes:
                    sizes.append(s)
            out.append(InputSource(path, kind, name, sizes, images=images, frames=len(images)))
    return out


# --------------------------------------------------------------------------------------------- cameras
@dataclass(frozen=True)
class _Plan:
    """How frames of one size reach the network: their camera, and the cylinder they are converted to."""

    camera: Camera
    convert_to: CylindricalCamera | None = None

    @property
    def network_input(self) -> Camera:
        return self.convert_to if self.convert_to is not None else self.camera


def _plan(
    source: InputSource,
    size: tuple[int, int],
    predictor: Predictor,
    vfov_h: float,
    camera: Camera | None,
    camera_path: str | None,
) -> _Plan:
    w, h = size
    target = model_camera(predictor, vfov_h)
    want = target.width / target.height
    if camera is None:
        if not _aspect_ok(w / h, want):
            raise CylsfmError(
                f"{source.path}: frames are {w}x{h} (aspect {w / h:.3f}) but the model takes full 360-degree "
                f"cylindrical panoramas of aspect {want:.3f} (width/height, e.g. {target.width}x{target.height}); "
                f"for other footage pass --camera camera.json describing it (cylindrical, equirectangular "
                f"or pinhole; see 'cylsfm camera')"
            )
        return _Plan(CylindricalCamera.full(w, h, vfov_h))
    cam = camera
    if cam.size != (w, h):
        if not _aspect_ok((w / h), cam.width / cam.height):
            raise CylsfmError(
                f"{source.path}: frames are {w}x{h} but {camera_path} describes {cam.width}x{cam.height} images"
            )
        cam = cam.resized(w, h)
    if isinstance(cam, PinholeCamera):
        raise CylsfmError(
            f"{camera_path}: a pinhole camera cannot feed this model, which was trained on full 360-degree "
            f"cylindrical panoramas; give it 360-degree footage (equirectangular or cylindrical)"
        )
    if isinstance(cam, CylindricalCamera | EquirectangularCamera) and not cam.wraps:
        raise CylsfmError(
            f"{camera_path}: a {cam.model} camera that does not cover 360 degrees (fx * 2 pi != width); "
            f"the model needs full panoramas"
        )
    if isinstance(cam, CylindricalCamera):
        cam_vfov = cam.height / (2.0 * float(cam.fy))
        centred = abs(float(cam.cy) - (cam.height - 1) / 2) <= 0.01 * cam.height
        if centred and _aspect_ok(cam_vfov, vfov_h):
            return _Plan(cam)
    elif not isinstance(cam, EquirectangularCamera):
        raise CylsfmError(f"{camera_path}: unsupported camera model {cam.model!r}")
    return _Plan(cam, convert_to=target)


# --------------------------------------------------------------------------------------------- frames
def _image_frames(source: InputSource) -> Iterator[tuple[str, np.ndarray]]:
    for path in source.images:
        yield path.stem, load_image(path)  # DatasetError (a CylsfmError) names a corrupt file


def _keep_times(fps: float | None) -> Callable[[float], bool]:
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


def _video_frames(source: InputSource, fps: float | None) -> Iterator[tuple[str, np.ndarray]]:
    av = _import_av()
    path = source.path
    rate = float(source.rate) if source.rate else float(_FALLBACK_RATE)
    keep = _keep_times(fps)
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
            t = frame.time if frame.time is not None else index / rate
            if not keep(t):
                continue
            yield f"{index:06d}", frame.to_ndarray(format="rgb24")
    if index < 0:
        raise CylsfmError(f"{path}: the video has no frames that can be decoded")


# --------------------------------------------------------------------------------------------- preview video
class _VideoWriter:
    """An mp4 written to a temporary name and renamed into place by :meth:`close`.

    Codec: h264 (libx264), or mpeg4 when FFmpeg has no libx264; yuv420p; frames padded with black to even
    sizes.
    """

    def __init__(self, path: Path, rate: Fraction) -> None:
        self.av = _import_av()
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


# --------------------------------------------------------------------------------------------- running
@dataclass
class PredictSummary:
    """What :func:`predict` wrote: frames per input name, and the preview videos."""

    frames: dict[str, int] = field(default_factory=dict)
    videos: list[Path] = field(default_factory=list)

    @property
    def total(self) -> int:
        return sum(self.frames.values())


def _to_uint8(images: torch.Tensor) -> np.ndarray:
    """``[B,3,H,W]`` in [0, 1] -> ``uint8 [B,H,W,3]``."""
    return (images.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


def _progress(total: int | None, enabled: bool):
    if enabled:
        try:
            from tqdm import tqdm

            return tqdm(total=total, unit="frame", desc="predict", dynamic_ncols=True)
        except ImportError:
            pass

    class _Null:
        def update(self, n: int = 1) -> None:
            pass

        def set_postfix_str(self, s: str) -> None:
            pass

        def close(self) -> None:
            pass

    return _Null()


def predict(
    checkpoint: str | os.PathLike[str] | Predictor,
    inputs: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    camera: str | os.PathLike[str] | Camera | None = None,
    batch_size: int = 8,
    device: str = "auto",
    png: bool = True,
    fps: float | None = None,
    progress: bool = True,
) -> PredictSummary:
    """Predict depth for images, image folders and videos; see the module docstring for the outputs.

    Args:
        checkpoint: a checkpoint file, a run directory, or a ready :class:`~cylsfm.model.Predictor`.
        inputs: image files, folders of images and video files.
        out: output directory (created).
        camera: the camera of every input (a ``camera.json`` path or a camera); ``None``: inputs must be
            full cylindrical panoramas of the model's aspect ratio.
        batch_size: frames per network call.
        device: ``auto``, ``cpu``, ``cuda``, ``cuda:N`` (ignored for a ready predictor).
        png: also write the coloured depth pictures.
        fps: take about this many frames a second from videos (and give the preview this rate); ``None``:
            every frame, at the video's own rate.
        progress: show a progress bar (tqdm) on stderr.

    Raises:
        CylsfmError: an input is missing, unreadable or corrupt, or its camera does not suit the model;
            the message names the file. Every input's cameras are checked before anything is written.
    """
    if batch_size < 1:
        raise CylsfmError(f"--batch-size must be at least 1, got {batch_size}")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise CylsfmError(f"--fps must be a positive number, got {fps}")
    sources = discover_inputs(inputs)
    cam: Camera | None
    camera_path: str | None
    if camera is None or isinstance(camera, Camera):
        cam, camera_path = camera, "the given camera" if camera is not None else None
    else:
        cam, camera_path = load_camera(camera), str(camera)

    predictor = (
        checkpoint if isinstance(checkpoint, Predictor) else Predictor.from_checkpoint(checkpoint, device)
    )
    vfov_h = model_vfov_h(predictor.config)
    plans: dict[tuple[str, tuple[int, int]], _Plan] = {}

    def plan_for(source: InputSource, size: tuple[int, int]) -> _Plan:
        key = (source.name, size)
        if key not in plans:
            plans[key] = _plan(source, size, predictor, vfov_h, cam, camera_path)
        return plans[key]

    for source in sources:  # refuse unsuitable inputs before writing anything
        for size in source.sizes:
            plan_for(source, size)

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    total: int | None = 0
    for s in sources:
        if s.kind == "video" and fps is not None and s.rate:
            s_frames = math.ceil(s.frames * min(1.0, fps / float(s.rate)))
        else:
            s_frames = s.frames
        total = None if (total is None or not s_frames) else total + s_frames
    bar = _progress(total, progress)
    summary = PredictSummary()
    try:
        with torch.inference_mode():
            for source in sources:
                _run_source(source, plan_for, predictor, out, batch_size, png, fps, bar, summary)
    finally:
        bar.close()
    return summary


def _run_source(
    source: InputSource,
    plan_for: Callable[[InputSource, tuple[int, int]], _Plan],
    predictor: Predictor,
    out: Path,
    batch_size: int,
    png: bool,
    fps: float | None,
    bar: Any,
    summary: PredictSummary,
) -> None:
    dest = out / source.name
    dest.mkdir(parents=True, exist_ok=True)
    summary.frames[source.name] = 0
    writer = None
    if source.kind == "video":
        rate = Fraction(fps).limit_denominator(1001) if fps else (source.rate or _FALLBACK_RATE)
        writer = _VideoWriter(out / f"{source.name}.mp4", rate)
    frames = _video_frames(source, fps) if source.kind == "video" else _image_frames(source)
    batch: list[tuple[str, np.ndarray]] = []

    def flush() -> None:
        if batch:
            _run_batch(batch, source, plan_for, predictor, dest, png, writer)
            summary.frames[source.name] += len(batch)
            bar.update(len(batch))
            batch.clear()

    try:
        for stem, rgb in frames:
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
    source: InputSource,
    plan_for: Callable[[InputSource, tuple[int, int]], _Plan],
    predictor: Predictor,
    dest: Path,
    png: bool,
    writer: _VideoWriter | None,
) -> None:
    h, w = batch[0][1].shape[:2]
    plan = plan_for(source, (w, h))
    dev = predictor.device
    frames = []
    for _, rgb in batch:
        # uint8 to the device (4x less to copy), then float; converted one frame at a time so that
        # large 360-degree frames never sit on the device as a whole batch
        x = (
            torch.from_numpy(np.require(rgb, np.uint8, ["C", "W"])).to(dev).permute(2, 0, 1)[None].float()
            / 255
        )
        if plan.convert_to is not None:
            x = to_cylinder(x, plan.camera, plan.convert_to).clamp(0, 1)
        frames.append(x)
    images = torch.cat(frames)
    cam = plan.network_input
    depth = predictor.depth(images, cam)[:, 0].float().cpu().numpy()
    shown = None
    if writer is not None:
        win = predictor.window(cam)
        shown = _to_uint8(images if win is None else images[..., win[0] : win[1]])
    for i, (stem, _) in enumerate(batch):
        save_depth(dest / f"{stem}.npy", depth[i])
        colour = colorize_depth(depth[i]) if (png or writer is not None) else None
        if png:
            save_png(dest / f"{stem}.png", colour)
        if writer is not None and shown is not None:
            writer.write(side_by_side([shown[i], colour]))
