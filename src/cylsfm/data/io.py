"""The single files of the cylsfm dataset format: frames, depth maps, masks and TUM pose files.

Reading: :func:`load_image` (``uint8 [H,W,3]`` RGB), :func:`load_depth` (``float32 [H,W]`` metres,
0 = unknown), :func:`load_mask` (``float32 [H,W]`` in ``{0, 1}``), :func:`read_tum` (camera-to-world
``float64 [N,4,4]``), and the header-only :func:`image_size` / :func:`depth_header` used to check a
dataset without decoding it. Every problem with a file raises :class:`DatasetError` naming the file.

Writing (atomically, temporary file + rename): :func:`save_png`, :func:`save_depth`, :func:`write_tum`.
The directory layout that holds these files is :mod:`cylsfm.data.format`.
"""

from __future__ import annotations

import io
import math
import os
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..atomic import atomic_write_bytes
from ..errors import CylsfmError, InputError, reading
from ..geometry import mat_to_tum, tum_to_mat

__all__ = [
    "DatasetError",
    "atomic_write_bytes",
    "depth_header",
    "image_size",
    "load_depth",
    "load_image",
    "load_mask",
    "parse_numbers",
    "read_text",
    "read_tum",
    "resize_nearest",
    "save_depth",
    "save_png",
    "write_tum",
]

PathLike = str | os.PathLike[str]


class DatasetError(CylsfmError, ValueError):
    """A dataset file is missing or invalid; the message names the file and the problem."""


# --------------------------------------------------------------------------------------- writing
# atomic_write_bytes (re-exported here for the data tools) lives in cylsfm.atomic
def save_png(path: PathLike, image: np.ndarray, compress_level: int = 6) -> None:
    """Write a ``uint8`` image ``[H,W,3]`` (RGB) or ``[H,W]`` (grey) as PNG, atomically."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise InputError(f"{path}: save_png needs a uint8 array, got {image.dtype}")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise InputError(f"{path}: save_png needs an [H,W,3] or [H,W] array, got shape {image.shape}")
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG", compress_level=compress_level)
    atomic_write_bytes(path, buf.getvalue())


def _checked_depth(depth: np.ndarray, path: PathLike, error: type[Exception]) -> np.ndarray:
    """``depth`` as float32 ``[H,W]`` after checking it is 2-D, finite and non-negative (``error`` if not)."""
    if depth.ndim != 2:
        raise error(f"{path}: depth must be a 2-D [H,W] array, got shape {depth.shape}")
    depth = depth.astype(np.float32, copy=False)
    if not np.isfinite(depth).all():
        raise error(f"{path}: depth has non-finite values (NaN or inf)")
    if (depth < 0).any():
        raise error(f"{path}: depth has negative values (use 0 for unknown)")
    return depth


def parse_numbers(parts: list[str], where: str, line: str) -> list[float]:
    """Finite floats from text fields; :class:`DatasetError` naming ``where`` (a file, a file:line) if not."""
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise DatasetError(f"{where}: not a number in {line!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise DatasetError(f"{where}: non-finite value in {line!r}")
    return values


def save_depth(path: PathLike, depth: np.ndarray) -> None:
    """Write a depth map ``[H,W]`` (metres, >= 0, 0 = unknown) as a float32 ``.npy`` file, atomically."""
    depth = _checked_depth(np.asarray(depth), path, InputError)
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(depth), allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def write_tum(
    path: PathLike, timestamps: np.ndarray | Sequence[float], c2w: np.ndarray, comments: Sequence[str] = ()
) -> None:
    """Write camera-to-world poses ``c2w [N,4,4]`` with ``timestamps [N]`` as a TUM file, atomically.

    One line per pose: ``t tx ty tz qx qy qz qw`` (translation in metres, unit quaternion, scalar last),
    after a header of ``#`` comment lines: the columns, then ``comments`` (one line each, e.g. the unit).
    """
    mats = np.asarray(c2w, dtype=np.float64)
    times = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if mats.ndim != 3 or mats.shape[1:] != (4, 4):
        raise InputError(f"{path}: poses must be [N,4,4], got shape {mats.shape}")
    if times.shape[0] != mats.shape[0]:
        raise InputError(f"{path}: {times.shape[0]} timestamps for {mats.shape[0]} poses")
    if not (np.isfinite(mats).all() and np.isfinite(times).all()):
        raise InputError(f"{path}: poses and timestamps must be finite")
    rot = mats[:, :3, :3]
    err = np.abs(rot.transpose(0, 2, 1) @ rot - np.eye(3)).max(initial=0.0)
    if err > 1e-5 or (mats.shape[0] and np.linalg.det(rot).min() <= 0):
        raise InputError(f"{path}: poses must be rigid transforms (orthonormal rotation, det +1)")
    tum = mat_to_tum(torch.from_numpy(mats)).numpy() if mats.shape[0] else np.zeros((0, 7))
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    lines += [f"# {line}" for c in comments for line in c.splitlines()]
    for t, row in zip(times, tum, strict=True):
        lines.append(" ".join(repr(float(v)) for v in (t, *row)))
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


# --------------------------------------------------------------------------------------- reading
def read_text(path: PathLike, what: str) -> str:
    """The text of a small file of the format (``what``: e.g. ``"pose file"``, named in errors).

    Raises :class:`DatasetError` ``"PATH: <what> not found"`` for a missing file and
    ``"PATH: cannot read (...)"`` for any other file-system or decoding error.
    """
    path = Path(path)
    with reading(path, DatasetError):
        if not path.exists():
            raise DatasetError(f"{path}: {what} not found")
        return path.read_text()


def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Returns ``(timestamps float64 [N], c2w float64 [N,4,4])``: camera-to-world transforms (metres).
    Blank lines and lines starting with ``#`` are skipped. A line that does not hold 8 finite numbers,
    or whose quaternion is zero, raises :class:`DatasetError` naming the file and the line number.
    """
    path = Path(path)
    text = read_text(path, "pose file")
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
        values = parse_numbers(parts, f"{path}:{lineno}", line)
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
    return _checked_depth(arr, path, DatasetError)


#: Serialises np.load: its header parsing (ast.literal_eval) fails at random when threads run it at once
#: ("AST constructor recursion depth mismatch"), and depth files are read by loader threads.
_NPY_HEADER_LOCK = threading.Lock()


def load_depth(path: PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Load a ground-truth depth map: ``float32 [H,W]`` in metres, 0 = unknown.

    Any integer or float dtype is converted to float32. With ``size = (W, H)`` the map is resampled by
    nearest neighbour (pixel centres, so 0 = unknown stays exact). A missing or unreadable file, a pickled
    object, a shape other than ``[H,W]``, non-finite or negative values raise :class:`DatasetError`.
    """
    path = Path(path)
    try:
        with _NPY_HEADER_LOCK:  # the .npy header is parsed by ast, which CPython 3.11 races across threads
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
