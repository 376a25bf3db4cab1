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

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from torch.utils.data import Dataset

from ..geometry import Camera, CameraError
from .dataset import AugmentConfig, build_sample, camera_class
from .format import DatasetError, image_size, load_image
from .splits import check_snippet_args

__all__ = ["StripDataset", "read_cam_txt"]


def read_cam_txt(path: str | os.PathLike[str]) -> tuple[float, float, float, float]:
    """``(fx, cx, fy, cy)`` (pixels) from a ``*_cam.txt`` file: 9 numbers ``fx,0,cx,0,fy,cy,0,0,1``."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"{path}: intrinsics file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read intrinsics file ({exc})") from None
    parts = text.replace(",", " ").split()
    if len(parts) != 9:
        raise DatasetError(
            f"{path}: expected 9 comma-separated numbers 'fx,0,cx,0,fy,cy,0,0,1', got {len(parts)}"
        )
    try:
        v = [float(p) for p in parts]
    except ValueError:
        raise DatasetError(f"{path}: not a number in {text.strip()!r}") from None
    if not all(math.isfinite(x) for x in v):
        raise DatasetError(f"{path}: non-finite intrinsics")
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
            raise ValueError(f"split must be a plain name such as 'train', got {split!r}")
        if size is not None:
            if len(size) != 2 or any(int(v) != v or v < 1 for v in size):
                raise ValueError(f"size must be (W, H) with positive integers, got {size!r}")
            size = (int(size[0]), int(size[1]))
        self.root = Path(root)
        self.seq_length = seq_length
        self.camera_model = camera_model
        self.size = size
        self.augment = augment
        list_path = self.root / f"{split}.txt"
        try:
            text = list_path.read_text()
        except FileNotFoundError:
            raise DatasetError(f"{list_path}: list file not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{list_path}: cannot read list file ({exc})") from None
        root_r = self.root.resolve()
        self._items: list[tuple[str, str, Path]] = []
        cams: list[Camera] = []
        frame_sizes: set[tuple[int, int]] = set()
        for lineno, raw in enumerate(text.splitlines(), 1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            if len(parts) != 2:
                raise DatasetError(f"{list_path}:{lineno}: expected 'SUBFOLDER FRAME_ID', got {line!r}")
            sub, fid = parts
            if not _safe_relative(sub) or not _safe_relative(fid) or "/" in fid:
                raise DatasetError(f"{list_path}:{lineno}: entry {line!r} would leave the dataset root")
            folder = self.root / sub
            image = next((p for p in (folder / f"{fid}.jpg", folder / f"{fid}.png") if p.exists()), None)
            if image is None:
                raise DatasetError(
                    f"{folder / fid}.jpg: strip image not found (nor .png), listed in {list_path}:{lineno}"
                )
            cam_path = folder / f"{fid}_cam.txt"
            for p in (image, cam_path):
                if p.exists() and not p.resolve().is_relative_to(root_r):
                    raise DatasetError(f"{p}: resolves outside the dataset root {root_r}")
            width, height = image_size(image)
            if width % seq_length:
                raise DatasetError(
                    f"{image}: strip width {width} is not a multiple of seq_length={seq_length}"
                )
            fx, cx, fy, cy = read_cam_txt(cam_path)
            fw = width // seq_length
            try:
                cam = cls(width=fw, height=height, fx=fx, cx=cx, fy=fy, cy=cy)
            except CameraError as exc:
                raise DatasetError(f"{cam_path}: {exc}") from None
            if size is not None and cam.size != size:
                cam = cam.resized(*size)
            cams.append(cam)
            frame_sizes.add((fw, height))
            self._items.append((sub, fid, image))
        if size is None and len(frame_sizes) > 1:
            raise DatasetError(
                f"{list_path}: strips have different frame sizes {sorted(frame_sizes)}; pass size=(W, H)"
            )
        if augment is not None and augment.roll:
            for (sub, fid, _), cam in zip(self._items, cams, strict=True):
                if not cam.wraps:
                    raise ValueError(
                        f"roll augmentation needs full 360-degree panoramas (fx * 2 pi == width); "
                        f"{sub}/{fid} does not wrap"
                    )
        self._intr = np.asarray([[float(c.fx), float(c.cx), float(c.fy), float(c.cy)] for c in cams])
        self._sizes = [c.size for c in cams]

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
