"""The cylsfm dataset format (v1): reading, checking and writing sequences of panoramic video.

A dataset root holds one directory per sequence (or is itself a single sequence)::

    ROOT/SEQ/camera.json         camera model and intrinsics (see cylsfm.geometry.Camera.to_dict)
    ROOT/SEQ/images/000000.png   RGB frames in time order (png or jpg), sorted by file name
    ROOT/SEQ/depth/000000.npy    optional: float32 [H,W] ground-truth depth in metres, 0 = unknown
    ROOT/SEQ/poses.txt           optional: TUM lines "t tx ty tz qx qy qz qw" (camera-to-world)
    ROOT/SEQ/mask.png            optional: white = pixels to use
    ROOT/splits/NAME/{train,val,test}.txt   optional split files (cylsfm.data.splits)

``docs/data-format.md`` describes the format in full. Every problem with a file raises
:class:`DatasetError`, whose message names the file and the problem.
"""

from __future__ import annotations

import io
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..atomic import atomic_write_bytes
from ..errors import CylsfmError
from ..geometry import Camera, CameraError, load_camera, mat_to_tum, tum_to_mat

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


class DatasetError(CylsfmError, ValueError):
    """A dataset file is missing or invalid; the message names the file and the problem."""


class DatasetWarning(UserWarning):
    """A bad frame was skipped (``skip_bad=True``); the message names the file and the problem."""


# --------------------------------------------------------------------------------------- writing
# atomic_write_bytes (re-exported here for the data tools) lives in cylsfm.atomic
def save_png(path: PathLike, image: np.ndarray, compress_level: int = 6) -> None:
    """Write a ``uint8`` image ``[H,W,3]`` (RGB) or ``[H,W]`` (grey) as PNG, atomically."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"{path}: save_png needs a uint8 array, got {image.dtype}")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ValueError(f"{path}: save_png needs an [H,W,3] or [H,W] array, got shape {image.shape}")
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG", compress_level=compress_level)
    atomic_write_bytes(path, buf.getvalue())


def save_depth(path: PathLike, depth: np.ndarray) -> None:
    """Write a depth map ``[H,W]`` (metres, >= 0, 0 = unknown) as a float32 ``.npy`` file, atomically."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"{path}: depth must be [H,W], got shape {depth.shape}")
    depth = depth.astype(np.float32, copy=False)
    if not np.isfinite(depth).all():
        raise ValueError(f"{path}: depth has non-finite values")
    if (depth < 0).any():
        raise ValueError(f"{path}: depth has negative values")
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(depth), allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def write_tum(path: PathLike, timestamps: np.ndarray | Sequence[float], c2w: np.ndarray) -> None:
    """Write camera-to-world poses ``c2w [N,4,4]`` with ``timestamps [N]`` as a TUM file, atomically.

    One line per pose: ``t tx ty tz qx qy qz qw`` (translation in metres, unit quaternion, scalar last).
    """
    mats = np.asarray(c2w, dtype=np.float64)
    times = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if mats.ndim != 3 or mats.shape[1:] != (4, 4):
        raise ValueError(f"{path}: poses must be [N,4,4], got shape {mats.shape}")
    if times.shape[0] != mats.shape[0]:
        raise ValueError(f"{path}: {times.shape[0]} timestamps for {mats.shape[0]} poses")
    if not (np.isfinite(mats).all() and np.isfinite(times).all()):
        raise ValueError(f"{path}: poses and timestamps must be finite")
    rot = mats[:, :3, :3]
    err = np.abs(rot.transpose(0, 2, 1) @ rot - np.eye(3)).max(initial=0.0)
    if err > 1e-5 or (mats.shape[0] and np.linalg.det(rot).min() <= 0):
        raise ValueError(f"{path}: poses must be rigid transforms (orthonormal rotation, det +1)")
    tum = mat_to_tum(torch.from_numpy(mats)).numpy() if mats.shape[0] else np.zeros((0, 7))
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    for t, row in zip(times, tum, strict=True):
        lines.append(" ".join(repr(float(v)) for v in (t, *row)))
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


# --------------------------------------------------------------------------------------- reading
def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Returns ``(timestamps float64 [N], c2w float64 [N,4,4])``: camera-to-world transforms (metres).
    Blank lines and lines starting with ``#`` are skipped. A line that does not hold 8 finite numbers,
    or whose quaternion is zero, raises :class:`DatasetError` naming the file and the line number.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"{path}: pose file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read pose file ({exc})") from None
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 8:
            raise DatasetError(
                f"{path}:{lineno}: expected 8 values 't tx ty tz qx qy qz qw', got {len(parts)}"
            )
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not a number in {line!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise DatasetError(f"{path}:{lineno}: non-finite value in {line!r}")
        if math.hypot(*values[4:]) < 1e-12:
            raise DatasetError(f"{path}:{lineno}: zero quaternion")
        rows.append(values)
    if not rows:
        return np.zeros(0, dtype=np.float64), np.zeros((0, 4, 4), dtype=np.float64)
    arr = np.asarray(rows, dtype=np.float64)
    c2w = tum_to_mat(torch.from_numpy(arr[:, 1:])).numpy()
    return arr[:, 0].copy(), c2w


def _open_error(path: Path, what: str, exc: BaseException) -> DatasetError:
    if isinstance(exc, FileNotFoundError):
        return DatasetError(f"{path}: {what} not found")
    detail = str(exc) or type(exc).__name__
    return DatasetError(f"{path}: cannot decode {what} ({detail})")


def _to_rgb(im: Image.Image) -> Image.Image:
    if im.mode == "RGB":
        return im
    if im.mode.startswith("I;16") or im.mode == "I":
        # 16-bit grey: scale to 8 bits (PIL's own conversion would clip at 255).
        arr = np.asarray(im).astype(np.float32) / 257.0
        grey = np.clip(np.rint(arr), 0, 255).astype(np.uint8)
        return Image.fromarray(grey).convert("RGB")
    return im.convert("RGB")


def load_image(path: PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Decode an image file to ``uint8 [H,W,3]`` RGB (grey, palette and RGBA images are converted).

    With ``size = (W, H)`` the image is resampled to that size with area interpolation (PIL's BOX filter).
    A missing, unreadable or corrupt file raises :class:`DatasetError` naming it.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            rgb = _to_rgb(im)
            if size is not None and rgb.size != tuple(size):
                rgb = rgb.resize((int(size[0]), int(size[1])), Image.Resampling.BOX)
            return np.asarray(rgb)
    except Exception as exc:
        raise _open_error(path, "image", exc) from None


def image_size(path: PathLike) -> tuple[int, int]:
    """``(W, H)`` of an image file from its header only (the pixels are not decoded)."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            return im.size
    except Exception as exc:
        raise _open_error(path, "image", exc) from None


def _check_depth_array(path: Path, arr: object) -> np.ndarray:
    if not isinstance(arr, np.ndarray):
        raise DatasetError(f"{path}: depth file must hold one array, got {type(arr).__name__}")
    if arr.dtype.kind not in "fiu":
        raise DatasetError(f"{path}: depth must be numeric, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise DatasetError(f"{path}: depth must be a 2-D [H,W] array, got shape {arr.shape}")
    depth = arr.astype(np.float32, copy=False)
    if not np.isfinite(depth).all():
        raise DatasetError(f"{path}: depth has non-finite values (NaN or inf)")
    if (depth < 0).any():
        raise DatasetError(f"{path}: depth has negative values (use 0 for unknown)")
    return depth


def load_depth(path: PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Load a ground-truth depth map: ``float32 [H,W]`` in metres, 0 = unknown.

    Any integer or float dtype is converted to float32. With ``size = (W, H)`` the map is resampled by
    nearest neighbour (pixel centres, so 0 = unknown stays exact). A missing or unreadable file, a pickled
    object, a shape other than ``[H,W]``, non-finite or negative values raise :class:`DatasetError`.
    """
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise _open_error(path, "depth file", exc) from None
    if isinstance(arr, np.lib.npyio.NpzFile):
        arr.close()
        raise DatasetError(f"{path}: depth file must be a .npy array, got an .npz archive")
    depth = _check_depth_array(path, arr)
    if size is not None and (depth.shape[1], depth.shape[0]) != tuple(size):
        depth = resize_nearest(depth, size)
    return np.ascontiguousarray(depth)


def resize_nearest(array: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resampling of ``[H,W,...]`` to ``size = (W', H')`` with pixel-centre alignment.

    Output pixel ``u'`` takes input column ``floor((u' + 0.5) W / W')``.
    """
    h, w = array.shape[:2]
    w2, h2 = int(size[0]), int(size[1])
    cols = np.minimum(((np.arange(w2) + 0.5) * (w / w2)).astype(np.int64), w - 1)
    rows = np.minimum(((np.arange(h2) + 0.5) * (h / h2)).astype(np.int64), h - 1)
    return array[rows[:, None], cols[None, :]]


def depth_header(path: PathLike) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` of a ``.npy`` file from its header only; :class:`DatasetError` if unreadable."""
    path = Path(path)
    fmt = np.lib.format
    try:
        with open(path, "rb") as fh:
            version = fmt.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = fmt.read_array_header_1_0(fh)
            elif version == (2, 0):
                shape, _, dtype = fmt.read_array_header_2_0(fh)
            else:
                arr = np.load(path, mmap_mode="r", allow_pickle=False)
                shape, dtype = arr.shape, arr.dtype
                del arr
    except Exception as exc:
        raise _open_error(path, "depth file", exc) from None
    return tuple(shape), np.dtype(dtype)


def load_mask(path: PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Load a mask image as ``float32 [H,W]`` in ``{0, 1}``: 1 where the (grey) value is above one half.

    With ``size = (W, H)`` the grey image is first resampled with area interpolation, so an output pixel
    is used when most of its area was.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            grey = _to_rgb(im).convert("L") if im.mode.startswith("I") else im.convert("L")
            if size is not None and grey.size != tuple(size):
                grey = grey.resize((int(size[0]), int(size[1])), Image.Resampling.BOX)
            arr = np.asarray(grey)
    except Exception as exc:
        raise _open_error(path, "mask", exc) from None
    return (arr > 127).astype(np.float32)


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


def _scan_sequence(seq_dir: Path, root: Path, skip_bad: bool) -> SequenceInfo:
    _checked(seq_dir, root)
    cam_path = _checked(seq_dir / "camera.json", root)
    try:
        camera = load_camera(cam_path)
    except CameraError as exc:
        raise DatasetError(str(exc)) from None
    images = list_images(seq_dir, root)
    n = len(images)
    bad: dict[int, str] = {}

    def problem(index: int, message: str) -> None:
        if not skip_bad:
            raise DatasetError(message)
        warnings.warn(f"{message}; frame skipped", DatasetWarning, stacklevel=4)
        bad.setdefault(index, message)

    want = camera.size
    for i, img in enumerate(images):
        try:
            got = image_size(img)
        except DatasetError as exc:
            problem(i, str(exc))
            continue
        if got != want:
            problem(
                i,
                f"{img}: image is {got[0]}x{got[1]} but camera.json says {want[0]}x{want[1]}",
            )

    depths: list[Path | None] | None = None
    depth_dir = seq_dir / "depth"
    if depth_dir.is_dir():
        _checked(depth_dir, root)
        index_of = {p.stem: i for i, p in enumerate(images)}
        found: list[Path | None] = [None] * n
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
            if i in bad:
                continue
            shape, dtype = depth_header(path)
            if dtype.kind not in "fiu":
                problem(i, f"{path}: depth must be numeric, got dtype {dtype}")
            elif shape != (want[1], want[0]):
                problem(i, f"{path}: depth is {shape} but the camera is [H,W] = ({want[1]}, {want[0]})")
        if any(p is not None for p in found):
            depths = found

    poses = timestamps = None
    pose_path = seq_dir / "poses.txt"
    if pose_path.exists():
        _checked(pose_path, root)
        timestamps, poses = read_tum(pose_path)
        if poses.shape[0] != n:
            raise DatasetError(f"{pose_path}: {poses.shape[0]} poses but {n} frames in {seq_dir / 'images'}")

    mask = None
    mask_path = seq_dir / "mask.png"
    if mask_path.exists():
        _checked(mask_path, root)
        got = image_size(mask_path)
        if got != want:
            raise DatasetError(
                f"{mask_path}: mask is {got[0]}x{got[1]} but camera.json says {want[0]}x{want[1]}"
            )
        mask = mask_path

    return SequenceInfo(
        name=seq_dir.name,
        path=seq_dir,
        camera=camera,
        images=images,
        depths=depths,
        poses=poses,
        timestamps=timestamps,
        mask=mask,
        bad=bad,
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
    dirs = find_sequence_dirs(root)
    return [_scan_sequence(Path(d), root_r, skip_bad) for d in dirs]


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
            raise ValueError(
                f"{self.path}: frames must be uint8 [{h},{w},3], got {image.dtype} {tuple(image.shape)}"
            )
        stem = f"{self.count:06d}"
        if depth is not None:
            depth = np.asarray(depth)
            if depth.shape != (h, w):
                raise ValueError(f"{self.path}: depth must be [{h},{w}], got {tuple(depth.shape)}")
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
            raise ValueError(f"{self.path}: no frames were added")
        if c2w is not None:
            mats = np.asarray(c2w, dtype=np.float64)
            if mats.shape != (self.count, 4, 4):
                raise ValueError(f"{self.path}: poses must be [{self.count},4,4], got {tuple(mats.shape)}")
            times = np.arange(self.count, dtype=np.float64) if timestamps is None else timestamps
            write_tum(self.path / "poses.txt", times, mats)
        elif timestamps is not None:
            raise ValueError(f"{self.path}: timestamps without poses")
        if mask is not None:
            m = np.asarray(mask)
            w, h = self.camera.size
            if m.shape != (h, w):
                raise ValueError(f"{self.path}: mask must be [{h},{w}], got {tuple(m.shape)}")
            if m.dtype == np.bool_ or (m.dtype == np.uint8 and m.max(initial=0) <= 1):
                m = m.astype(np.uint8) * 255
            if m.dtype != np.uint8:
                raise ValueError(f"{self.path}: mask must be bool or uint8, got {m.dtype}")
            save_png(self.path / "mask.png", m)
        self.camera.to_json(self.path / "camera.json")
        self._finished = True
        return self.path
