"""Training and evaluation samples (snippets of consecutive frames) from datasets in the cylsfm format.

:class:`SequenceDataset` loads the snippets of a :class:`~cylsfm.data.index.SnippetIndex` (built once by
:func:`~cylsfm.data.index.build_index`: the dataset's scan, bad-frame and static-frame removal, the split)
as samples (:mod:`cylsfm.data.sample`), augmented (:mod:`cylsfm.data.augment`) for training, as its
:class:`SampleOptions` say. The names of those modules are re-exported here::

    index = build_index(root, split="train", seq_length=3, static=StaticFilter("auto"))
    dataset = SequenceDataset(index, SampleOptions(size=(512, 128), augment=AugmentConfig()))
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch.utils.data import Dataset

from ..errors import InputError, reading
from ..geometry import Camera, relative_pose
from .augment import AugmentConfig
from .cache import FrameCache, available_memory_bytes
from .format import DatasetError, DatasetWarning, load_depth, load_image, load_mask
from .geometry import RideGeometry, load_geometry
from .index import SnippetIndex, build_index
from .sample import NUM_SCALES, build_sample, camera_class, camera_of, check_size, intrinsics_pyramid
from .static import StaticFilter

__all__ = [
    "NUM_SCALES",
    "AugmentConfig",
    "SampleOptions",
    "SequenceDataset",
    "SnippetIndex",
    "StaticFilter",
    "build_index",
    "build_sample",
    "camera_class",
    "camera_of",
    "intrinsics_pyramid",
]


@dataclass(frozen=True)
class SampleOptions:
    """How a :class:`SequenceDataset` loads its snippets.

    Attributes:
        size: ``(W, H)`` to resample images to (area interpolation; depth by nearest neighbour; the camera
            via ``Camera.resized``), or ``None`` for the stored size (then all sequences must share it).
        augment: :class:`AugmentConfig`, or ``None`` for no augmentation.
        ground_truth: include ``"depth"`` and ``"pose_gt"`` when available.
        cache: decode every frame of the samples once, up front, and keep it in memory as ``uint8``
            (:class:`~cylsfm.data.cache.FrameCache`); samples are then the same as without it, faster.
            ``"auto"``: only when the frames take at most a quarter of the memory still available.
        mask: an image of the pixels to use in every sequence (white), e.g. without a helmet seen in every
            frame, of the panoramas' aspect ratio (resampled to their size): it multiplies each sequence's
            own ``mask.png`` and, being part of each sample, follows the augmentation (a mirrored sample has
            a mirrored mask).
        geometry: a folder with the rides' own adjusted geometry, one :func:`cylsfm.odometry` output per
            ride named as the ride (:mod:`cylsfm.data.geometry`): each sample then has ``"sfm_depth"``,
            ``"sfm_pose"`` and ``"sfm_step"``. A ride without its folder gives no target (``sfm_step`` 0).

    Raises:
        InputError: for an invalid ``size`` or ``cache``; a ``ValueError`` too.
    """

    size: tuple[int, int] | None = None
    augment: AugmentConfig | None = None
    ground_truth: bool = True
    cache: bool | str = False
    mask: str | os.PathLike[str] | None = None
    geometry: str | os.PathLike[str] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "size", check_size(self.size))
        if self.cache not in (True, False, "auto"):
            raise InputError(f"cache must be True, False or 'auto', got {self.cache!r}")


class SequenceDataset(Dataset):
    """The snippets of ``index`` as samples, loaded as ``options`` say (default :class:`SampleOptions`).

    Every sample is a dictionary (only keys present in every sample of the dataset appear, so the default
    ``torch.utils.data.default_collate`` works):

    - ``"target"``: ``float32 [3,H,W]`` in ``[0, 1]``, the middle frame of the snippet;
    - ``"sources"``: ``float32 [S,3,H,W]``, the other ``S = seq_length - 1`` frames in time order;
    - ``"intrinsics"``: ``float32 [4,4]``, row ``s`` = ``(fx, cx, fy, cy)`` in pixels at scale ``s``,
      image size ``(ceil(W / 2^s), ceil(H / 2^s))`` (:func:`intrinsics_pyramid`);
    - ``"camera_model"``: ``"cylindrical"`` or ``"pinhole"``; ``"size"``: ``(W, H)``;
    - ``"depth"``: ``float32 [1,H,W]`` ground-truth depth of the target in metres (the camera model's
      depth), 0 = unknown; present when any used sequence has depth (frames without are all 0);
    - ``"pose_gt"``: ``float32 [S,4,4]`` ground-truth ``T_tgt_to_src = relative_pose(c2w_tgt, c2w_src)``
      (metres); present when every used sequence has ``poses.txt``;
    - ``"mask"``: ``float32 [1,H,W]`` in ``{0, 1}``, 1 = pixel to use; present when any used sequence has
      ``mask.png`` or ``options.mask`` is given (sequences without get all ones);
    - ``"sfm_depth"``: ``float32 [4,H,W]``, with ``options.geometry``: the ride's adjusted points seen by the
      target, channel 0 their depth in the ride's unit (0 = none), channel 1 its relative standard deviation;
      channel 2 the target's depth fused with its neighbours' by the adjusted poses (0 = none: the odometry
      wrote no depth maps), channel 3 its spread in log depth
      (:meth:`~cylsfm.data.geometry.RideGeometry.targets`);
      ``"sfm_pose"``: ``float32 [S,4,4]`` the adjusted ``T_tgt_to_src`` per source, in the ride's unit;
      ``"sfm_step"``: ``float32 [S]``, the ride's median step length in its unit where it has its geometry
      (else 0, the pose the identity);
    - ``"sequence"``: sequence name; ``"frame"``: the target's frame name; ``"index"``: the sample's index.

    Use :func:`camera_of` to get the (possibly augmented) camera of a sample or a batch. With an index
    built with ``skip_bad``, a sample whose frame fails to decode is replaced by the next loadable one
    (warned about, deterministic) instead of raising :class:`DatasetError`.

    Raises:
        DatasetError: sequences of different sizes without ``options.size``; a mask of another aspect
            ratio than the panoramas; at load time, naming the file, a corrupt image or depth map (unless
            the index skips bad frames).
    """

    def __init__(self, index: SnippetIndex, options: SampleOptions | None = None) -> None:
        options = options if options is not None else SampleOptions()
        self.index = index
        self.options = options
        self.root = index.root
        self.sequences = index.sequences
        self.size = options.size
        self.augment = options.augment
        self.skip_bad = index.skip_bad
        self.center = index.center
        self.cameras: list[Camera] = self._resized_cameras()
        self._snippets, self._seq_idx = index.frames, index.owners
        used_seqs = [self.sequences[s] for s in index.used]
        self.has_depth = options.ground_truth and any(s.depths is not None for s in used_seqs)
        self.has_pose = (
            options.ground_truth and bool(used_seqs) and all(s.poses is not None for s in used_seqs)
        )
        self.extra_mask = Path(options.mask) if options.mask is not None else None
        self._check_extra_mask(index.used)
        self.has_mask = self.extra_mask is not None or any(s.mask is not None for s in used_seqs)
        # found at load time (per process): frames that fail to decode ((seq, -1): the mask), and
        # targets whose depth map is bad
        self._bad_frames: set[tuple[int, int]] = set()
        self._bad_targets: set[tuple[int, int]] = set()
        self._mask_cache: dict[int, np.ndarray] = {}
        self.frame_cache = self._frame_cache(options.cache) if len(index) else None
        self.geometry = self._geometry(options.geometry)

    # ------------------------------------------------------------------ building
    def _resized_cameras(self) -> list[Camera]:
        """The camera of every sequence at the dataset's image size (all sequences must share one
        without ``size``)."""
        size = self.size
        sizes = {s.camera.size for s in self.sequences}
        if size is None and len(sizes) > 1:
            detail = ", ".join(f"{s.name}: {s.camera.width}x{s.camera.height}" for s in self.sequences)
            raise DatasetError(f"{self.root}: sequences differ in image size ({detail}); pass size=(W, H)")
        return [
            s.camera if size is None or s.camera.size == size else s.camera.resized(*size)
            for s in self.sequences
        ]

    def _frame_cache(self, cache: bool | str) -> FrameCache | None:
        """Every frame of the snippets decoded once at the dataset's size, if ``cache`` asks for it
        (``"auto"``: when they take at most a quarter of the free memory)."""
        if not cache:
            return None
        pairs = zip(self._seq_idx.tolist(), self._snippets.tolist(), strict=True)
        keys = sorted({(s, f) for s, row in pairs for f in row})
        camera = self.cameras[keys[0][0]]
        shape = (camera.height, camera.width)
        free = available_memory_bytes()
        if cache == "auto" and free is not None and FrameCache.nbytes(len(keys), shape) > free // 4:
            return None
        return FrameCache(keys, shape, self._decode)

    def _geometry(self, folder: str | os.PathLike[str] | None) -> dict[int, RideGeometry | None] | None:
        """Each used sequence's adjusted geometry from ``folder/<its name>`` (``None`` where it has none),
        or ``None`` without a folder."""
        if folder is None:
            return None
        root = Path(folder)
        if not root.is_dir():
            raise DatasetError(f"{root}: no such folder of the rides' geometry")
        out: dict[int, RideGeometry | None] = {}
        for s in self.index.used:
            seq = self.sequences[s]
            ride = root / seq.name
            if not ride.resolve().is_relative_to(root.resolve()):
                raise DatasetError(f"{root}: the ride {seq.name!r} names a folder outside it")
            stems = [p.stem for p in seq.images]
            out[s] = load_geometry(ride, len(seq.images), seq.camera, stems) if ride.is_dir() else None
        return out

    def _decode(self, s: int, f: int) -> np.ndarray:
        """Frame ``f`` of sequence ``s`` as ``uint8 [H,W,3]`` at the dataset's size."""
        seq, camera = self.sequences[s], self.cameras[s]
        return load_image(seq.images[f], camera.size if camera.size != seq.camera.size else None)

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return int(self._snippets.shape[0])

    def targets(self) -> list[tuple[str, str]]:
        """``(sequence, frame)`` of every sample's target, in index order."""
        return self.index.targets()

    def snippet(self, index: int) -> tuple[str, list[str]]:
        """``(sequence, frame names of the snippet in time order)`` of sample ``index``."""
        return self.index.snippet(index)

    def __getitem__(self, index: int) -> dict[str, Any]:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for a dataset of {n} samples")
        index %= n
        if not self.skip_bad:
            return self._load(index)
        for step in range(n):
            j = (index + step) % n
            if self._known_bad(j):
                continue
            try:
                return self._load(j)
            except DatasetError as exc:
                warnings.warn(
                    f"{exc}; sample {j} replaced by the next loadable one", DatasetWarning, stacklevel=2
                )
        raise DatasetError(f"{self.root}: no loadable sample left (every snippet has a bad frame)")

    def _known_bad(self, j: int) -> bool:
        if not (self._bad_frames or self._bad_targets):
            return False
        s = int(self._seq_idx[j])
        frames = self._snippets[j]
        return (
            (s, -1) in self._bad_frames
            or (s, int(frames[self.center])) in self._bad_targets
            or any((s, int(f)) in self._bad_frames for f in frames)
        )

    def _load(self, j: int) -> dict[str, Any]:
        s = int(self._seq_idx[j])
        seq = self.sequences[s]
        camera = self.cameras[s]
        size = camera.size if camera.size != seq.camera.size else None
        frames = self._snippets[j]
        images = []
        for f in frames.tolist():
            try:
                images.append(self.frame_cache.get(s, f) if self.frame_cache else self._decode(s, f))
            except DatasetError:
                self._bad_frames.add((s, f))
                raise
        tgt = int(frames[self.center])
        depth = self._target_depth(s, tgt, size) if self.has_depth else None
        mask = self._sequence_mask(s, size) if self.has_mask else None
        pose_gt = None
        src = [int(f) for k, f in enumerate(frames) if k != self.center]
        if self.has_pose:
            c2w = torch.from_numpy(seq.poses)
            pose_gt = relative_pose(c2w[tgt].expand(len(src), 4, 4), c2w[src]).numpy()
        sfm = None
        if self.geometry is not None:
            ride = self.geometry.get(s)
            if ride is None:
                w, h = camera.size
                sfm = (
                    np.zeros((4, h, w), np.float32),
                    np.tile(np.eye(4), (len(src), 1, 1)),
                    np.zeros(len(src)),
                )
            else:
                sfm = (
                    ride.targets(tgt, camera.size),
                    ride.relative(tgt, src),
                    np.full(len(src), ride.step),
                )
        return build_sample(
            np.stack(images),
            camera,
            self.augment,
            sequence=seq.name,
            frame=seq.images[tgt].stem,
            index=j,
            depth=depth,
            mask=mask,
            pose_gt=pose_gt,
            sfm=sfm,
        )

    def _target_depth(self, s: int, tgt: int, size: tuple[int, int] | None) -> np.ndarray:
        """``float32 [H,W]`` depth (metres) of frame ``tgt`` of sequence ``s``; all 0 where it has none."""
        path = self.sequences[s].depth_path(tgt)
        if path is None:
            camera = self.cameras[s]
            return np.zeros((camera.height, camera.width), dtype=np.float32)
        try:
            return load_depth(path, size)
        except DatasetError:
            self._bad_targets.add((s, tgt))
            raise

    def _check_extra_mask(self, used: list[int]) -> None:
        """The extra mask must have the panoramas' aspect ratio (it is resampled to their size, never
        squashed): an equirectangular mask of a cylinder is refused."""
        if self.extra_mask is None:
            return
        with reading(self.extra_mask, DatasetError):
            with Image.open(self.extra_mask) as im:
                mw, mh = im.size
        for s in used:
            cam = self.cameras[s]
            if abs(mw * cam.height - mh * cam.width) > 0.01 * mh * cam.width:
                raise DatasetError(
                    f"{self.extra_mask}: a {mw}x{mh} mask for {cam.width}x{cam.height} panoramas "
                    f"({self.sequences[s].name}): give a mask of the panoramas' size or aspect ratio "
                    "(cylsfm prepare --mask converts an equirectangular one)"
                )

    def _sequence_mask(self, s: int, size: tuple[int, int] | None) -> np.ndarray:
        """``float32 [H,W]`` mask of sequence ``s`` (cached): its own ``mask.png`` times the dataset's extra
        mask; all ones where there is neither."""
        mask = self._mask_cache.get(s)
        if mask is not None:
            return mask
        seq, camera = self.sequences[s], self.cameras[s]
        if seq.mask is None:
            mask = np.ones((camera.height, camera.width), dtype=np.float32)
        else:
            try:
                mask = load_mask(seq.mask, size)
            except DatasetError:
                self._bad_frames.add((s, -1))
                raise
        if self.extra_mask is not None:
            mask = mask * load_mask(self.extra_mask, (camera.width, camera.height))
        self._mask_cache[s] = mask
        return mask
