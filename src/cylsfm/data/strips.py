"""Read-only support for the prepared format of the original SfMLearner and CylindricalSfMLearner code.

Layout::

    ROOT/train.txt, ROOT/val.txt       lines "SUBFOLDER FRAME_ID"
    ROOT/SUBFOLDER/FRAME_ID.jpg        (or .png) seq_length frames side by side: width = seq_length * W;
                                       the target is the middle frame, the others are the sources in order
    ROOT/SUBFOLDER/FRAME_ID_cam.txt    the 3x3 intrinsics of one frame, 9 comma-separated numbers
                                       "fx,0,cx,0,fy,cy,0,0,1"

Strips carry no ground truth. Frames are stored once per sample (duplicated between samples), so the
cylsfm format (:mod:`cylsfm.data.format`) is preferred for new data.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from torch.utils.data import Dataset

from ..errors import InputError
from ..geometry import Camera, CameraError
from .augment import AugmentConfig
from .io import DatasetError, image_size, load_image, parse_numbers, read_text
from .sample import build_sample, camera_class, check_size
from .splits import check_snippet_args

__all__ = ["StripDataset", "is_strip_dataset", "read_cam_txt"]


def is_strip_dataset(root: str | os.PathLike[str]) -> bool:
    """Whether ``root`` holds strips prepared for the original SfMLearner code: a ``train.txt`` list and no
    sequence of the cylsfm format (no ``*/camera.json``)."""
    root = Path(root)
    return (root / "train.txt").is_file() and not any(root.glob("*/camera.json"))


def read_cam_txt(path: str | os.PathLike[str]) -> tuple[float, float, float, float]:
    """``(fx, cx, fy, cy)`` (pixels) from a ``*_cam.txt`` file: 9 numbers ``fx,0,cx,0,fy,cy,0,0,1``."""
    path = Path(path)
    text = read_text(path, "intrinsics file")
    parts = text.replace(",", " ").split()
    if len(parts) != 9:
        raise DatasetError(
            f"{path}: expected 9 comma-separated numbers 'fx,0,cx,0,fy,cy,0,0,1', got {len(parts)}"
        )
    v = parse_numbers(parts, str(path), text.strip())
    return v[0], v[2], v[4], v[5]


def _safe_relative(name: str) -> bool:
    if not name or os.path.isabs(name) or "\\" in name or "\x00" in name or name.startswith("~"):
        return False
    return all(part not in ("", ".", "..") for part in name.split("/"))


class StripDataset(Dataset):
    """Samples of an SfMLearner-prepared dataset (image strips), with the keys of
    :class:`~cylsfm.data.SequenceDataset` (no ground truth: no ``depth``, ``pose_gt`` or ``mask``).

    Args:
        root: the prepared dataset's root.
        split: the list file ``ROOT/<split>.txt`` (``"train"`` or ``"val"``).
        seq_length: frames per strip (odd); the target is the middle one.
        camera_model: ``"cylindrical"`` or ``"pinhole"``: the model of ``cam.txt``'s intrinsics. A
            cylindrical camera whose ``fx * 2 pi`` equals the frame width is a full panorama and wraps.
        size: ``(W, H)`` of one frame to resample to (area interpolation), or ``None``.
        augment: :class:`~cylsfm.data.AugmentConfig`, or ``None``.

    Raises:
        DatasetError: naming the file, for a missing list, image or ``cam.txt``, a listed path that
            leaves the root (absolute or ``..``), a strip whose width is not a multiple of
            ``seq_length``, or strips of different sizes without ``size``.
        InputError: for invalid arguments (an even ``seq_length``, a split that is not a plain name, an
            unknown camera model); a ``ValueError`` too.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        split: str = "train",
        seq_length: int = 3,
        camera_model: str = "cylindrical",
        size: tuple[int, int] | None = None,
        augment: AugmentConfig | None = None,
    ) -> None:
        check_snippet_args(seq_length, 1)
        cls = camera_class(camera_model)
        if not split or "/" in split or "\\" in split or split in (".", ".."):
            raise InputError(f"split must be a plain name such as 'train', got {split!r}")
        self.root = Path(root)
        self.seq_length = seq_length
        self.camera_model = camera_model
        self.size = check_size(size)
        self.augment = augment
        list_path = self.root / f"{split}.txt"
        text = read_text(list_path, "list file")
        root_r = self.root.resolve()
        self._items: list[tuple[str, str, Path]] = []
        cams: list[Camera] = []
        frame_sizes: set[tuple[int, int]] = set()
        for lineno, raw in enumerate(text.splitlines(), 1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            sub, fid, image, cam_path = self._entry(line, f"{list_path}:{lineno}", root_r)
            cam = self._strip_camera(cls, image, cam_path)
            frame_sizes.add(cam.size)
            if self.size is not None and cam.size != self.size:
                cam = cam.resized(*self.size)
            cams.append(cam)
            self._items.append((sub, fid, image))
        if self.size is None and len(frame_sizes) > 1:
            raise DatasetError(
                f"{list_path}: strips have different frame sizes {sorted(frame_sizes)}; pass size=(W, H)"
            )
        self._intr = np.asarray([[float(c.fx), float(c.cx), float(c.fy), float(c.cy)] for c in cams])
        self._sizes = [c.size for c in cams]

    def _entry(self, line: str, where: str, root_r: Path) -> tuple[str, str, Path, Path]:
        """``(subfolder, frame id, strip image, cam.txt)`` of a list line (``where``: its file and line)."""
        parts = line.split()
        if len(parts) != 2:
            raise DatasetError(f"{where}: expected 'SUBFOLDER FRAME_ID', got {line!r}")
        sub, fid = parts
        if not _safe_relative(sub) or not _safe_relative(fid) or "/" in fid:
            raise DatasetError(f"{where}: entry {line!r} would leave the dataset root")
        folder = self.root / sub
        image = next((p for p in (folder / f"{fid}.jpg", folder / f"{fid}.png") if p.exists()), None)
        if image is None:
            raise DatasetError(f"{folder / fid}.jpg: strip image not found (nor .png), listed in {where}")
        cam_path = folder / f"{fid}_cam.txt"
        for p in (image, cam_path):
            if p.exists() and not p.resolve().is_relative_to(root_r):
                raise DatasetError(f"{p}: resolves outside the dataset root {root_r}")
        return sub, fid, image, cam_path

    def _strip_camera(self, cls: type[Camera], image: Path, cam_path: Path) -> Camera:
        """The camera of one frame of a strip (its stored size), from the image header and ``cam.txt``."""
        width, height = image_size(image)
        if width % self.seq_length:
            raise DatasetError(
                f"{image}: strip width {width} is not a multiple of seq_length={self.seq_length}"
            )
        fx, cx, fy, cy = read_cam_txt(cam_path)
        try:
            return cls(width=width // self.seq_length, height=height, fx=fx, cx=cx, fy=fy, cy=cy)
        except CameraError as exc:
            raise DatasetError(f"{cam_path}: {exc}") from None

    def __len__(self) -> int:
        return len(self._items)

    def camera(self, index: int) -> Camera:
        """The (resized, not augmented) camera of sample ``index``."""
        fx, cx, fy, cy = self._intr[index].tolist()
        w, h = self._sizes[index]
        return camera_class(self.camera_model)(width=w, height=h, fx=fx, cx=cx, fy=fy, cy=cy)

    def __getitem__(self, index: int) -> dict[str, Any]:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for a dataset of {n} samples")
        index %= n
        sub, fid, image = self._items[index]
        strip = load_image(image)
        h, width = strip.shape[:2]
        if width % self.seq_length:
            raise DatasetError(
                f"{image}: strip width {width} is not a multiple of seq_length={self.seq_length}"
            )
        fw = width // self.seq_length
        frames = strip.reshape(h, self.seq_length, fw, 3).transpose(1, 0, 2, 3)
        camera = self.camera(index)
        if camera.size != (fw, h):
            frames = np.stack(
                [np.asarray(Image.fromarray(f).resize(camera.size, Image.Resampling.BOX)) for f in frames]
            )
        return build_sample(
            np.ascontiguousarray(frames), camera, self.augment, sequence=sub, frame=fid, index=index
        )
