"""``cylsfm prepare views``: the frames of a rig of pinhole views that share a centre (cube faces, a
multi-camera rig) stitched into one cylindrical sequence, with depth and poses when the rig has them.

A rig is described by a JSON file (paths relative to it, never outside its folder)::

    {
      "views": [
        {"name": "front", "images": "front", "camera": "front.json", "yaw": 0},
        {"name": "right", "images": "right", "depth": "right_depth", "camera": {...}, "yaw": 90,
         "pitch": 0, "roll": 0},
        ...
      ],
      "depth_scale": 0.01,        # depth files' unit in metres (16-bit PNG in centimetres: 0.01)
      "depth_invalid": 65535,     # a raw depth value from this one up is unknown (optional)
      "poses": "poses.txt",       # TUM camera-to-world of the rig, one line per frame (optional)
      "fps": 5                    # frame rate for the poses' times when there are no poses (optional)
    }

A view's ``camera`` is a camera.json file or its contents (pinhole); ``yaw`` turns it right, ``pitch`` up,
``roll`` about its axis (degrees; :func:`~cylsfm.data.stitch.view_rotation`). The rig's frame, the
panorama's, is the frame of a view with yaw, pitch and roll 0. Frames are matched by file stem across the
views (their names must sort in time order, e.g. zero-padded numbers: the poses file's lines are matched
to them in that order); a frame missing in one view is an error. Depth files are ``.npy`` (metres) or images read unchanged
(16-bit PNG; the first channel) times ``depth_scale``, along each view's optical axis.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import CylsfmError
from ...geometry import Camera, CylindricalCamera, load_camera
from ..format import IMAGE_SUFFIXES
from ..io import load_depth, load_image, read_text, read_tum
from ..stitch import Stitcher, View, view_rotation
from .sequence import PreparedSequence

__all__ = ["RigFrame", "RigOptions", "load_rig", "prepare_views", "read_view_depth", "write_rig"]


@dataclass(frozen=True)
class RigOptions:
    """How a rig is prepared.

    Attributes:
        size: the panorama's ``(W, H)``.
        vfov_h: its rows span ``h`` in ``[-vfov_h, vfov_h]``; pixels that no view sees are black and left
            out by the sequence's ``mask.png``.
        camera: the output camera exactly (overrides ``size`` and ``vfov_h``).
        exclude: frame names to leave out.
        static_motion: leave out a frame whose pose moved less than this many metres (and turned less
            than ``static_turn_deg``) since the last kept frame (needs poses; 0: keep every frame).
        static_turn_deg: see ``static_motion``.
    """

    size: tuple[int, int] = (512, 128)
    vfov_h: float = 1.0
    camera: CylindricalCamera | None = None
    exclude: frozenset[str] = field(default_factory=frozenset)
    static_motion: float = 0.0
    static_turn_deg: float = 1.0

    def output_camera(self) -> CylindricalCamera:
        if self.camera is not None:
            return self.camera
        w, h = self.size
        if w < 8 or h < 8 or not (self.vfov_h > 0 and math.isfinite(self.vfov_h)):
            raise CylsfmError(
                f"the panorama must be at least 8x8 with vfov_h > 0, got {w}x{h}, {self.vfov_h}"
            )
        return CylindricalCamera.full(int(w), int(h), float(self.vfov_h))

    def settings(self) -> dict[str, Any]:
        return {
            "camera": self.output_camera().to_dict(),
            "exclude": sorted(self.exclude),
            "static": [self.static_motion, self.static_turn_deg],
        }


@dataclass
class RigFrame:
    """One frame of a rig: the views' image files (and depth files), its time and the rig's pose."""

    name: str
    images: list[Path]
    depths: list[Path] | None = None
    time: float = 0.0
    pose: np.ndarray | None = None


def read_view_depth(path: Path, scale: float, invalid: float | None) -> np.ndarray:
    """A view's depth file: ``float32 [H,W]`` metres along its optical axis, 0 unknown.

    ``.npy``: metres (:func:`~cylsfm.data.io.load_depth`); other files (16-bit PNG ...) are read unchanged
    (first channel) and multiplied by ``scale``; raw values ``>= invalid`` are unknown.
    """
    if path.suffix.lower() == ".npy":
        return load_depth(path)
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise CylsfmError(f"{path}: not a readable depth image")
    if raw.ndim == 3:
        raw = raw[..., 0]  # the channels hold the same value (SYNTHIA); OpenCV reads BGR
    depth = raw.astype(np.float64)
    if invalid is not None:
        depth[depth >= invalid] = 0.0
    return (depth * scale).astype(np.float32)


def drop_static(frames: list[RigFrame], motion: float, turn_deg: float) -> tuple[list[RigFrame], int]:
    """The frames kept when those that moved less than ``motion`` metres and turned less than
    ``turn_deg`` since the last kept frame are left out (their poses decide; the first is kept)."""
    if motion <= 0:
        return frames, 0
    kept: list[RigFrame] = []
    for f in frames:
        if f.pose is None:
            raise CylsfmError(f"frame {f.name}: leaving out static frames needs the rig's poses")
        if kept:
            last = kept[-1].pose
            assert last is not None
            rel = np.linalg.inv(last) @ f.pose
            angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(rel[:3, :3]) - 1) / 2))))
            if np.linalg.norm(rel[:3, 3]) < motion and angle < turn_deg:
                continue
        kept.append(f)
    return kept, len(frames) - len(kept)


def write_rig(
    seq: PreparedSequence,
    stitcher: Stitcher,
    frames: Sequence[RigFrame],
    depth_scale: float = 1.0,
    depth_invalid: float | None = None,
    bar: Any = None,
) -> int:
    """Stitch and write every frame not written yet, then finish the sequence (mask, poses, camera).

    Returns the number of frames written in this call.
    """
    new = 0
    try:
        for f in frames:
            if bar is not None:
                bar.update(1)
            if seq.has(f.name):
                continue
            colour = stitcher.colour([load_image(p) for p in f.images])
            depth = None
            if f.depths is not None:
                depth = stitcher.depth([read_view_depth(p, depth_scale, depth_invalid) for p in f.depths])
            seq.add(f.name, colour, depth)
            new += 1
    finally:
        seq.wait()
    mask = None if stitcher.coverage.all() else stitcher.coverage
    with_poses = all(f.pose is not None for f in frames)
    poses = {f.name: (f.time, f.pose) for f in frames} if with_poses else None
    seq.finish(mask, poses)  # type: ignore[arg-type]
    return new


def _inside(path: Path, root: Path, what: str) -> Path:
    resolved = path.resolve()
    if not resolved.is_relative_to(root.resolve()):
        raise CylsfmError(f"{path}: the {what} lies outside the rig's folder {root}")
    return path


def _files(folder: Path, suffixes: Sequence[str]) -> dict[str, Path]:
    if not folder.is_dir():
        raise CylsfmError(f"{folder}: folder not found")
    out = {}
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") or p.suffix.lower() not in suffixes:
            continue
        out[p.stem] = _inside(p, folder, "file") if p.is_symlink() else p
    return out


def _number(
    spec: dict[str, Any], key: str, default: float | None, where: str, positive: bool = False
) -> float | None:
    """``spec[key]`` as a finite number (``default`` when absent), else a :class:`CylsfmError`."""
    value = spec.get(key, default)
    if value is None:
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise CylsfmError(f"{where}: '{key}' must be a number, got {value!r}") from None
    if not math.isfinite(number) or (positive and number <= 0):
        raise CylsfmError(
            f"{where}: '{key}' must be a {'positive' if positive else 'finite'} number, got {value!r}"
        )
    return number


def _view(entry: Any, root: Path, i: int, rig: Path) -> tuple[View, dict[str, Path], dict[str, Path] | None]:
    where = f"{rig}: view {i}"
    if not isinstance(entry, dict) or "images" not in entry or "camera" not in entry:
        raise CylsfmError(f"{where} needs 'images' and 'camera'")
    name = str(entry.get("name", i))
    cam_entry = entry["camera"]
    if isinstance(cam_entry, dict):
        camera: Camera = Camera.from_dict(cam_entry, source=f"{where} camera")
    else:
        camera = load_camera(_inside(root / str(cam_entry), root, "camera file"))
    angles = [float(_number(entry, k, 0.0, where)) for k in ("yaw", "pitch", "roll")]  # type: ignore[arg-type]
    view = View(name, camera, view_rotation(*angles))
    images = _files(_inside(root / str(entry["images"]), root, "image folder"), IMAGE_SUFFIXES)
    depths = None
    if entry.get("depth") is not None:
        depths = _files(_inside(root / str(entry["depth"]), root, "depth folder"), (".npy", ".png", ".exr"))
    return view, images, depths


def load_rig(path: str | os.PathLike[str]) -> tuple[list[View], list[RigFrame], dict[str, Any]]:
    """Read a rig file: ``(views, frames in order, {"depth_scale", "depth_invalid"})``.

    Raises:
        CylsfmError: naming the file: not JSON, a view without images or camera, a path outside the rig's
            folder, a frame missing in a view or without depth, poses that do not match the frames.
    """
    path = Path(path)
    root = path.parent
    try:
        spec = json.loads(read_text(path, "rig file"))
    except ValueError as exc:
        raise CylsfmError(f"{path}: not a JSON rig file ({exc})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("views"), list) or not spec["views"]:
        raise CylsfmError(f"{path}: a rig file needs a non-empty list 'views'")
    parsed = [_view(e, root, i, path) for i, e in enumerate(spec["views"])]
    views = [v for v, _, _ in parsed]
    names = sorted(set().union(*(imgs.keys() for _, imgs, _ in parsed)))
    frames = []
    for n in names:
        for v, imgs, depths in parsed:
            if n not in imgs:
                raise CylsfmError(f"{path}: frame {n} is missing in view {v.name}")
            if depths is not None and n not in depths:
                raise CylsfmError(f"{path}: frame {n} has no depth file in view {v.name}")
        with_depth = all(d is not None for _, _, d in parsed)
        frames.append(
            RigFrame(
                n, [imgs[n] for _, imgs, _ in parsed], [d[n] for _, _, d in parsed] if with_depth else None
            )  # type: ignore[index]
        )
    _attach_poses(spec, root, path, frames)
    depth = {
        "depth_scale": _number(spec, "depth_scale", 1.0, str(path), positive=True),
        "depth_invalid": _number(spec, "depth_invalid", None, str(path)),
    }
    return views, frames, depth


def _attach_poses(spec: dict[str, Any], root: Path, path: Path, frames: list[RigFrame]) -> None:
    fps = float(_number(spec, "fps", 1.0, str(path), positive=True))  # type: ignore[arg-type]
    for i, f in enumerate(frames):
        f.time = i / fps
    if spec.get("poses") is None:
        return
    times, poses = read_tum(_inside(root / str(spec["poses"]), root, "pose file"))
    if len(poses) != len(frames):
        raise CylsfmError(f"{path}: {len(poses)} poses for {len(frames)} frames")
    for f, t, pose in zip(frames, times, poses, strict=True):
        f.time, f.pose = float(t), pose


def prepare_views(
    rig: str | os.PathLike[str],
    out: str | os.PathLike[str],
    options: RigOptions | None = None,
    name: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> tuple[Path, int, int]:
    """Stitch a rig's frames into the sequence ``OUT/NAME`` (``NAME``: the rig file's folder name).

    Returns ``(sequence directory, frames in it, frames left out as static)``.
    """
    from ...runtime import fingerprint, progress_bar

    options = options or RigOptions()
    views, frames, depth = load_rig(rig)
    frames = [f for f in frames if f.name not in options.exclude]
    frames, dropped = drop_static(frames, options.static_motion, options.static_turn_deg)
    camera = options.output_camera()
    seq_name = name or Path(rig).resolve().parent.name
    settings = {
        "rig": str(Path(rig).resolve()),
        # what decides the output: each view's camera and direction, the depth's unit, the poses
        "views": fingerprint(
            [[v.name, v.camera.to_dict(), np.round(v.rotation, 9).tolist()] for v in views]
            + [
                depth,
                [[f.name, f.time, None if f.pose is None else np.round(f.pose, 9).tolist()] for f in frames],
            ]
        ),
        **options.settings(),
    }
    seq = PreparedSequence(Path(out) / seq_name, camera, settings, overwrite)
    if not seq.finished:
        with progress_bar(total=len(frames), desc=seq_name, unit="frame", enabled=progress) as bar:
            write_rig(seq, Stitcher(views, camera), frames, depth["depth_scale"], depth["depth_invalid"], bar)
    return seq.path, len(seq.done), dropped
