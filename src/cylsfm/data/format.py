"""The cylsfm dataset format (v1): the layout of a dataset, found and checked, and written sequence by sequence.

A dataset root holds one directory per sequence (or is itself a single sequence)::

    ROOT/SEQ/camera.json         camera model and intrinsics (see cylsfm.geometry.Camera.to_dict)
    ROOT/SEQ/images/000000.png   RGB frames in time order (png or jpg), sorted by file name
    ROOT/SEQ/depth/000000.npy    optional: float32 [H,W] ground-truth depth in metres, 0 = unknown
    ROOT/SEQ/poses.txt           optional: TUM lines "t tx ty tz qx qy qz qw" (camera-to-world)
    ROOT/SEQ/mask.png            optional: white = pixels to use
    ROOT/splits/NAME/{train,val,test}.txt   optional split files (cylsfm.data.splits)

:func:`scan_dataset` finds and checks the sequences from file headers only (:class:`SequenceInfo`);
:class:`SequenceWriter` writes one. The single files are read and written by :mod:`cylsfm.data.io`
(re-exported here). ``docs/data-format.md`` describes the format in full. Every problem with a file raises
:class:`DatasetError`, whose message names the file and the problem.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import Camera, CameraError, load_camera
from .io import (
    DatasetError,
    atomic_write_bytes,
    depth_header,
    image_size,
    load_depth,
    load_image,
    load_mask,
    read_tum,
    resize_nearest,
    save_depth,
    save_png,
    write_tum,
)

__all__ = [
    "IMAGE_SUFFIXES",
    "DatasetError",
    "DatasetWarning",
    "SequenceInfo",
    "SequenceWriter",
    "atomic_write_bytes",
    "depth_header",
    "find_sequence_dirs",
    "image_size",
    "list_images",
    "load_depth",
    "load_image",
    "load_mask",
    "read_tum",
    "resize_nearest",
    "save_depth",
    "save_png",
    "scan_dataset",
    "write_tum",
]

#: File name suffixes (lower case) of frames in ``images/``.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

PathLike = str | os.PathLike[str]


class DatasetWarning(UserWarning):
    """A bad frame was skipped (``skip_bad=True``); the message names the file and the problem."""


# --------------------------------------------------------------------------------------- scanning
@dataclass
class SequenceInfo:
    """One sequence of a dataset, as found by :func:`scan_dataset` (nothing is decoded).

    Attributes:
        name: the sequence directory's name.
        path: the sequence directory.
        camera: its camera (``camera.json``), at the stored image size.
        images: the frames, in time order (sorted by file name).
        depths: ``None`` when no frame has ground-truth depth; otherwise one entry per frame: the
            ``.npy`` path, or ``None`` for a frame without depth.
        poses: ground-truth camera-to-world transforms ``float64 [N,4,4]`` (metres), or ``None``.
        timestamps: ``float64 [N]`` from ``poses.txt``, or ``None``.
        mask: ``mask.png`` (white = pixels to use), or ``None``.
        bad: frames found bad at scan time with ``skip_bad=True``: index -> problem. They are never
            used as targets or sources.
    """

    name: str
    path: Path
    camera: Camera
    images: list[Path]
    depths: list[Path | None] | None = None
    poses: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    mask: Path | None = None
    bad: dict[int, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def stems(self) -> list[str]:
        """Frame names (image file names without suffix), in time order."""
        return [p.stem for p in self.images]

    def depth_path(self, index: int) -> Path | None:
        """The depth file of frame ``index``, or ``None``."""
        return None if self.depths is None else self.depths[index]


def _inside(path: Path, root: Path) -> bool:
    return path == root or path.is_relative_to(root)


def _checked(path: Path, root: Path) -> Path:
    """``path`` if it resolves (symlinks followed) inside ``root`` (already resolved), else DatasetError."""
    real = path.resolve()
    if not _inside(real, root):
        raise DatasetError(f"{path}: resolves to {real}, outside the dataset root {root}")
    return path


def find_sequence_dirs(root: PathLike) -> list[Path]:
    """The sequence directories of a dataset root, sorted by name (no file is read).

    ``root`` itself when it holds ``camera.json``; otherwise its immediate subdirectories that hold
    ``camera.json`` or ``images/`` (hidden ones skipped). A subdirectory with ``images/`` but no
    ``camera.json`` raises :class:`DatasetError`; so does a root without any sequence.
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset root not found or not a directory")
    if (root / "camera.json").exists():
        # normalised (not resolved), so that "." or "seq/.." still name the sequence
        return [Path(os.path.abspath(root))]
    seqs = []
    for child in sorted(root.iterdir(), key=lambda p: p.name):
        if child.name.startswith(".") or not child.is_dir():
            continue
        has_cam = (child / "camera.json").exists()
        if not has_cam and (child / "images").is_dir():
            raise DatasetError(
                f"{child / 'camera.json'}: missing camera.json (sequence {child.name} has images/)"
            )
        if has_cam:
            seqs.append(child)
    if not seqs:
        raise DatasetError(
            f"{root}: no sequences found (expected ROOT/camera.json or ROOT/SEQ/camera.json + ROOT/SEQ/images/)"
        )
    return seqs


def list_images(seq_dir: PathLike, root: PathLike | None = None) -> list[Path]:
    """The frames in ``seq_dir/images`` (png/jpg, hidden files skipped), sorted by file name.

    With ``root`` (resolved) every path must resolve inside it. Raises :class:`DatasetError` when
    ``images/`` is missing or empty, or two frames share a name.
    """
    seq_dir = Path(seq_dir)
    img_dir = seq_dir / "images"
    if not img_dir.is_dir():
        raise DatasetError(f"{img_dir}: images directory not found")
    root_r = Path(root).resolve() if root is not None else None
    if root_r is not None:
        _checked(img_dir, root_r)
    names = []
    with os.scandir(img_dir) as it:
        for entry in it:
            if entry.name.startswith(".") or os.path.splitext(entry.name)[1].lower() not in IMAGE_SUFFIXES:
                continue
            if root_r is not None and entry.is_symlink():
                _checked(Path(entry.path), root_r)
            names.append(entry.name)
    if not names:
        raise DatasetError(f"{img_dir}: no images (expected .png or .jpg frames)")
    names.sort()
    stems: dict[str, str] = {}
    for name in names:
        stem = os.path.splitext(name)[0]
        if stem in stems:
            raise DatasetError(f"{img_dir / name}: two frames named {stem!r} ({stems[stem]} and {name})")
        stems[stem] = name
    return [img_dir / n for n in names]


class _FrameProblems:
    """Frame-level problems of one sequence: raised, or (``skip_bad``) warned about and recorded in ``bad``."""

    def __init__(self, skip_bad: bool) -> None:
        self.skip_bad = skip_bad
        self.bad: dict[int, str] = {}

    def report(self, index: int, message: str) -> None:
        if not self.skip_bad:
            raise DatasetError(message)
        # the warning points at the caller of scan_dataset (report < check < _scan_sequence < scan_dataset)
        warnings.warn(f"{message}; frame skipped", DatasetWarning, stacklevel=5)
        self.bad.setdefault(index, message)


def _check_image_sizes(images: list[Path], want: tuple[int, int], problems: _FrameProblems) -> None:
    """Every frame's header must be readable and its size ``want = (W, H)``."""
    for i, img in enumerate(images):
        try:
            got = image_size(img)
        except DatasetError as exc:
            problems.report(i, str(exc))
            continue
        if got != want:
            problems.report(i, f"{img}: image is {got[0]}x{got[1]} but camera.json says {want[0]}x{want[1]}")


def _find_depths(
    seq_dir: Path, root: Path, images: list[Path], want: tuple[int, int], problems: _FrameProblems
) -> list[Path | None] | None:
    """The depth file of every frame (``None`` for a frame without), or ``None`` when there is none.

    Every ``depth/*.npy`` must name a frame; its header must be numeric ``[H,W]`` of the camera's size.
    """
    depth_dir = seq_dir / "depth"
    if not depth_dir.is_dir():
        return None
    _checked(depth_dir, root)
    index_of = {p.stem: i for i, p in enumerate(images)}
    found: list[Path | None] = [None] * len(images)
    with os.scandir(depth_dir) as it:
        entries = sorted(
            (e for e in it if not e.name.startswith(".") and e.name.endswith(".npy")),
            key=lambda e: e.name,
        )
    for entry in entries:
        path = Path(entry.path)
        if entry.is_symlink():
            _checked(path, root)
        stem = path.stem
        if stem not in index_of:
            raise DatasetError(f"{path}: depth file without a matching image in {seq_dir / 'images'}")
        i = index_of[stem]
        found[i] = path
        if i in problems.bad:
            continue
        shape, dtype = depth_header(path)
        if dtype.kind not in "fiu":
            problems.report(i, f"{path}: depth must be numeric, got dtype {dtype}")
        elif shape != (want[1], want[0]):
            problems.report(i, f"{path}: depth is {shape} but the camera is [H,W] = ({want[1]}, {want[0]})")
    return found if any(p is not None for p in found) else None


def _read_poses(seq_dir: Path, root: Path, n: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(timestamps [N], c2w [N,4,4])`` from ``poses.txt`` (one pose per frame), or ``(None, None)``."""
    pose_path = seq_dir / "poses.txt"
    if not pose_path.exists():
        return None, None
    _checked(pose_path, root)
    timestamps, poses = read_tum(pose_path)
    if poses.shape[0] != n:
        raise DatasetError(f"{pose_path}: {poses.shape[0]} poses but {n} frames in {seq_dir / 'images'}")
    return timestamps, poses


def _find_mask(seq_dir: Path, root: Path, want: tuple[int, int]) -> Path | None:
    """``mask.png`` (of the camera's size ``want = (W, H)``), or ``None``."""
    mask_path = seq_dir / "mask.png"
    if not mask_path.exists():
        return None
    _checked(mask_path, root)
    got = image_size(mask_path)
    if got != want:
        raise DatasetError(f"{mask_path}: mask is {got[0]}x{got[1]} but camera.json says {want[0]}x{want[1]}")
    return mask_path


def _scan_sequence(seq_dir: Path, root: Path, skip_bad: bool) -> SequenceInfo:
    _checked(seq_dir, root)
    cam_path = _checked(seq_dir / "camera.json", root)
    try:
        camera = load_camera(cam_path)
    except CameraError as exc:
        raise DatasetError(str(exc)) from None
    images = list_images(seq_dir, root)
    problems = _FrameProblems(skip_bad)
    _check_image_sizes(images, camera.size, problems)
    depths = _find_depths(seq_dir, root, images, camera.size, problems)
    timestamps, poses = _read_poses(seq_dir, root, len(images))
    mask = _find_mask(seq_dir, root, camera.size)
    return SequenceInfo(
        name=seq_dir.name,
        path=seq_dir,
        camera=camera,
        images=images,
        depths=depths,
        poses=poses,
        timestamps=timestamps,
        mask=mask,
        bad=problems.bad,
    )


def scan_dataset(root: PathLike, skip_bad: bool = False) -> list[SequenceInfo]:
    """Find and check every sequence of a dataset without decoding pixels.

    Checks (from file headers only): ``camera.json`` is valid; ``images/`` is not empty; every image has
    the camera's size; every depth file matches an image, is numeric and ``[H,W]``; ``poses.txt`` has one
    valid line per frame; ``mask.png`` has the camera's size; no path resolves outside ``root``.

    Args:
        root: a dataset root, or a single sequence directory (it holds ``camera.json``).
        skip_bad: frame-level problems (an unreadable image header, a frame or depth map of the wrong
            size) drop the frame with a :class:`DatasetWarning` (recorded in ``SequenceInfo.bad``) instead
            of raising. Sequence-level problems always raise.

    Returns:
        The sequences, sorted by name.

    Raises:
        DatasetError: naming the offending file and the problem.
    """
    root_r = Path(root).resolve()
    sequences = []
    for d in find_sequence_dirs(root):
        sequences.append(_scan_sequence(Path(d), root_r, skip_bad))
    return sequences


# --------------------------------------------------------------------------------------- writer
class SequenceWriter:
    """Write one sequence in the dataset format, frame by frame.

    ``add_frame`` writes ``images/NNNNNN.png`` (and ``depth/NNNNNN.npy``) atomically; ``finish`` writes
    ``poses.txt``, ``mask.png`` and, last, ``camera.json``: a sequence without ``camera.json`` is
    unfinished. Frame names have 6 digits (up to a million frames keep their order).

    Args:
        seq_dir: the sequence directory (created).
        camera: the camera of the frames (its size is checked for every frame).
        overwrite: allow writing into a directory that already holds a sequence; its ``camera.json``,
            frames, depth maps, ``poses.txt`` and ``mask.png`` are removed first.
        compress_level: PNG compression (0-9; lower is faster to write, larger files).

    Raises:
        DatasetError: the directory already holds a sequence and ``overwrite`` is off.
        InputError: a frame, depth map, pose array or mask of the wrong shape or type.
    """

    def __init__(
        self, seq_dir: PathLike, camera: Camera, overwrite: bool = False, compress_level: int = 6
    ) -> None:
        self.path = Path(seq_dir)
        self.camera = camera
        self.compress_level = compress_level
        self.count = 0
        self._finished = False
        img_dir, depth_dir = self.path / "images", self.path / "depth"
        existing = (self.path / "camera.json").exists() or (img_dir.is_dir() and any(img_dir.iterdir()))
        if existing:
            if not overwrite:
                raise DatasetError(
                    f"{self.path}: already holds a sequence (pass overwrite=True to replace it)"
                )
            (self.path / "camera.json").unlink(missing_ok=True)
            for d, suffixes in ((img_dir, IMAGE_SUFFIXES), (depth_dir, (".npy",))):
                if d.is_dir():
                    for p in d.iterdir():
                        if p.suffix.lower() in suffixes:
                            p.unlink()
            for name in ("poses.txt", "mask.png"):
                (self.path / name).unlink(missing_ok=True)
        img_dir.mkdir(parents=True, exist_ok=True)

    def add_frame(self, image: np.ndarray, depth: np.ndarray | None = None) -> int:
        """Append a frame: ``image uint8 [H,W,3]`` RGB, optional ``depth [H,W]`` (metres, 0 = unknown).

        Returns the frame's index.
        """
        if self._finished:
            raise RuntimeError(f"{self.path}: sequence already finished")
        image = np.asarray(image)
        w, h = self.camera.size
        if image.dtype != np.uint8 or image.shape != (h, w, 3):
            raise InputError(
                f"{self.path}: frames must be uint8 [{h},{w},3], got {image.dtype} {tuple(image.shape)}"
            )
        stem = f"{self.count:06d}"
        if depth is not None:
            depth = np.asarray(depth)
            if depth.shape != (h, w):
                raise InputError(f"{self.path}: depth must be [{h},{w}], got {tuple(depth.shape)}")
            save_depth(self.path / "depth" / f"{stem}.npy", depth)
        save_png(self.path / "images" / f"{stem}.png", image, self.compress_level)
        self.count += 1
        return self.count - 1

    def finish(
        self,
        c2w: np.ndarray | None = None,
        timestamps: np.ndarray | Sequence[float] | None = None,
        mask: np.ndarray | None = None,
    ) -> Path:
        """Write the optional files, then ``camera.json``; returns the sequence directory.

        Args:
            c2w: ground-truth camera-to-world poses ``[N,4,4]`` (metres), one per frame -> ``poses.txt``.
            timestamps: ``[N]`` seconds for ``poses.txt`` (default: the frame indices).
            mask: ``[H,W]`` pixels to use -> ``mask.png``: ``True`` (bool) or 255 (uint8); a uint8 mask
                whose values are only 0 and 1 is read as 0/1 and stored as 0/255.
        """
        if self._finished:
            raise RuntimeError(f"{self.path}: sequence already finished")
        if self.count == 0:
            raise InputError(f"{self.path}: no frames were added")
        if c2w is not None:
            mats = np.asarray(c2w, dtype=np.float64)
            if mats.shape != (self.count, 4, 4):
                raise InputError(f"{self.path}: poses must be [{self.count},4,4], got {tuple(mats.shape)}")
            times = np.arange(self.count, dtype=np.float64) if timestamps is None else timestamps
            write_tum(self.path / "poses.txt", times, mats)
        elif timestamps is not None:
            raise InputError(f"{self.path}: timestamps without poses")
        if mask is not None:
            save_png(self.path / "mask.png", self._mask_image(mask))
        self.camera.to_json(self.path / "camera.json")
        self._finished = True
        return self.path

    def _mask_image(self, mask: np.ndarray) -> np.ndarray:
        """``uint8 [H,W]`` 0/255 image of a bool or uint8 mask of the camera's size."""
        m = np.asarray(mask)
        w, h = self.camera.size
        if m.shape != (h, w):
            raise InputError(f"{self.path}: mask must be [{h},{w}], got {tuple(m.shape)}")
        if m.dtype == np.bool_ or (m.dtype == np.uint8 and m.max(initial=0) <= 1):
            m = m.astype(np.uint8) * 255
        if m.dtype != np.uint8:
            raise InputError(f"{self.path}: mask must be bool or uint8, got {m.dtype}")
        return m
