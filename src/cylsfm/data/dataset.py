"""Training and evaluation samples (snippets of consecutive frames) from datasets in the cylsfm format.

:class:`SequenceDataset` forms the snippets of a dataset (after bad-frame and static-frame removal, and
restricted to a split) and loads them as samples (:mod:`cylsfm.data.sample`), augmented
(:mod:`cylsfm.data.augment`) for training. The names of those modules are re-exported here.
"""

from __future__ import annotations

import os
import warnings
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
from .format import (
    DatasetError,
    DatasetWarning,
    SequenceInfo,
    load_depth,
    load_image,
    load_mask,
    scan_dataset,
)
from .sample import NUM_SCALES, build_sample, camera_class, camera_of, check_size, intrinsics_pyramid
from .splits import SPLIT_PARTS, check_snippet_args, read_split, snippet_offsets, split_path
from .static import StaticFilter, kept_runs

__all__ = [
    "NUM_SCALES",
    "AugmentConfig",
    "SequenceDataset",
    "StaticFilter",
    "build_sample",
    "camera_class",
    "camera_of",
    "intrinsics_pyramid",
]


class SequenceDataset(Dataset):
    """Snippets of consecutive frames from a dataset in the cylsfm format (``docs/data-format.md``).

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
      ``mask.png`` (sequences without get all ones);
    - ``"sequence"``: sequence name; ``"frame"``: the target's frame name; ``"index"``: the sample's index.

    Use :func:`camera_of` to get the (possibly augmented) camera of a sample or a batch.

    Args:
        root: dataset root (or a single sequence directory).
        seq_length: frames per snippet (odd); the snippet of target ``t`` is
            ``t - k*stride .. t + k*stride`` with ``k = (seq_length - 1) // 2``, counted over the frames
            left after static-frame removal.
        stride: frame step within a snippet.
        split: ``None`` for every target with a full snippet; ``"train"``, ``"val"`` or ``"test"`` for
            ``ROOT/splits/<split_name>/<split>.txt``; or the path of a split file. Listed targets without
            a full snippet here (static frame, sequence border, bad frame) are skipped with one warning.
        split_name: which split of ``ROOT/splits`` a named split refers to.
        size: ``(W, H)`` to resample images to (area interpolation; depth by nearest neighbour; the camera
            via ``Camera.resized``), or ``None`` for the stored size (then all sequences must share it).
        augment: :class:`AugmentConfig`, or ``None`` for no augmentation.
        static: :class:`StaticFilter`; default ``StaticFilter(method="none")``.
        skip_bad: drop frames whose header is bad at build time (with a :class:`DatasetWarning`; no snippet
            contains them) and replace a sample whose frame fails to decode at load time by the next
            loadable one (warned about, deterministic) instead of raising :class:`DatasetError`.
        load_ground_truth: include ``"depth"`` and ``"pose_gt"`` when available.
        cache: decode every frame of the samples once, up front, and keep it in memory as ``uint8``
            (:class:`~cylsfm.data.cache.FrameCache`); samples are then the same as without it, faster.
            ``"auto"``: only when the frames take at most a quarter of the memory still available.
        mask: an image of the pixels to use in every sequence (white), e.g. without a helmet seen in every
            frame, of the panoramas' aspect ratio (resampled to their size): it multiplies each sequence's
            own ``mask.png`` and, being part of each sample, follows the augmentation (a mirrored sample has
            a mirrored mask).

    Raises:
        DatasetError: naming the file, for any invalid input (see :func:`scan_dataset`); at load time for a
            corrupt image or depth map (unless ``skip_bad``).
        InputError: for invalid arguments (even ``seq_length``);
            a ``ValueError`` too.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        seq_length: int = 3,
        stride: int = 1,
        split: str | os.PathLike[str] | None = None,
        split_name: str = "default",
        size: tuple[int, int] | None = None,
        augment: AugmentConfig | None = None,
        static: StaticFilter | None = None,
        skip_bad: bool = False,
        load_ground_truth: bool = True,
        cache: bool | str = False,
        mask: str | os.PathLike[str] | None = None,
    ) -> None:
        check_snippet_args(seq_length, stride)
        self.root = Path(root)
        self.seq_length = seq_length
        self.stride = stride
        self.size = check_size(size)
        self.augment = augment
        self.static = static if static is not None else StaticFilter(method="none")
        self.skip_bad = skip_bad
        self.load_ground_truth = load_ground_truth
        self.sequences: list[SequenceInfo] = scan_dataset(self.root, skip_bad=skip_bad)
        self.cameras: list[Camera] = self._resized_cameras()
        table, seq_arr = self._snippet_table()
        if split is not None:
            table, seq_arr = self._select_split(table, seq_arr, self._split_file(split, split_name))
        if len(table) == 0:
            warnings.warn(
                f"{self.root}: no samples (no target has a full snippet of seq_length={seq_length}, "
                f"stride={stride}{'' if split is None else f' in split {split}'})",
                DatasetWarning,
                stacklevel=2,
            )
        self._snippets = table
        self._seq_idx = seq_arr
        self.center = seq_length // 2
        used = sorted(set(seq_arr.tolist()))
        used_seqs = [self.sequences[s] for s in used]
        self.has_depth = load_ground_truth and any(s.depths is not None for s in used_seqs)
        self.has_pose = load_ground_truth and bool(used_seqs) and all(s.poses is not None for s in used_seqs)
        self.extra_mask = Path(mask) if mask is not None else None
        self._check_extra_mask(used)
        self.has_mask = self.extra_mask is not None or any(s.mask is not None for s in used_seqs)
        # found at load time (per process): frames that fail to decode ((seq, -1): the mask), and
        # targets whose depth map is bad
        self._bad_frames: set[tuple[int, int]] = set()
        self._bad_targets: set[tuple[int, int]] = set()
        self._mask_cache: dict[int, np.ndarray] = {}
        self.frame_cache = self._frame_cache(cache) if len(table) else None

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

    def _snippet_table(self) -> tuple[np.ndarray, np.ndarray]:
        """Every full snippet over the frames left after bad-frame and static-frame removal.

        Returns ``(frames int64 [N, seq_length], sequence int64 [N])``: the frame indices of each snippet
        in time order and the index of its sequence.
        """
        offsets = snippet_offsets(self.seq_length, self.stride)  # positions in the list of kept frames
        reach = int(offsets[-1])
        tables: list[np.ndarray] = [np.zeros((0, self.seq_length), dtype=np.int64)]
        owners: list[np.ndarray] = [np.zeros(0, dtype=np.int64)]
        for s, seq in enumerate(self.sequences):
            # the warnings of skipped frames point at the caller of SequenceDataset
            for kept in kept_runs(seq, self.static, self.skip_bad, stacklevel=3):
                if len(kept) <= 2 * reach:
                    continue
                pos = np.arange(reach, len(kept) - reach)[:, None] + offsets[None, :]
                tables.append(np.asarray(kept, dtype=np.int64)[pos])
                owners.append(np.full(len(pos), s, dtype=np.int64))
        return np.concatenate(tables), np.concatenate(owners)

    def _split_file(self, split: str | os.PathLike[str], split_name: str) -> Path:
        """The split file of a named part (``"train"``, ``"val"``, ``"test"``), which must exist, or ``split``."""
        if isinstance(split, str) and split in SPLIT_PARTS:
            path = split_path(self.root, split, split_name)
            if not path.exists():
                raise DatasetError(
                    f"{path}: split file not found (write the splits with `cylsfm split {self.root}`, "
                    "or use --split all)"
                )
            return path
        return Path(split)

    def _select_split(
        self, table: np.ndarray, seq_arr: np.ndarray, path: Path
    ) -> tuple[np.ndarray, np.ndarray]:
        """The rows of the snippet table whose targets the split file lists, in the file's order."""
        entries = read_split(path, self.root, self.sequences)
        seq_of_name = {seq.name: i for i, seq in enumerate(self.sequences)}
        frame_of = [{stem: i for i, stem in enumerate(seq.stems)} for seq in self.sequences]
        centres = table[:, self.seq_length // 2]
        where = {(s, f): n for n, (s, f) in enumerate(zip(seq_arr.tolist(), centres.tolist(), strict=True))}
        chosen = []
        for seq_name, stem in entries:
            s = seq_of_name[seq_name]
            n = where.get((s, frame_of[s][stem]))
            if n is not None:
                chosen.append(n)
        missing = len(entries) - len(chosen)
        if missing:
            warnings.warn(
                f"{path}: {missing} of {len(entries)} targets have no full snippet "
                f"(seq_length={self.seq_length}, stride={self.stride}, static={self.static.method}) "
                "and are skipped",
                DatasetWarning,
                stacklevel=3,
            )
        idx = np.asarray(chosen, dtype=np.int64)
        return (table[idx] if len(idx) else table[:0]), seq_arr[idx]

    def _frame_cache(self, cache: bool | str) -> FrameCache | None:
        """Every frame of the snippets decoded once at the dataset's size, if ``cache`` asks for it
        (``"auto"``: when they take at most a quarter of the free memory)."""
        if cache not in (True, False, "auto"):
            raise InputError(f"cache must be True, False or 'auto', got {cache!r}")
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

    def _decode(self, s: int, f: int) -> np.ndarray:
        """Frame ``f`` of sequence ``s`` as ``uint8 [H,W,3]`` at the dataset's size."""
        seq, camera = self.sequences[s], self.cameras[s]
        return load_image(seq.images[f], camera.size if camera.size != seq.camera.size else None)

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return int(self._snippets.shape[0])

    def targets(self) -> list[tuple[str, str]]:
        """``(sequence, frame)`` of every sample's target, in index order."""
        return [
            (self.sequences[s].name, self.sequences[s].images[row[self.center]].stem)
            for s, row in zip(self._seq_idx.tolist(), self._snippets, strict=True)
        ]

    def snippet(self, index: int) -> tuple[str, list[str]]:
        """``(sequence, frame names of the snippet in time order)`` of sample ``index``."""
        seq = self.sequences[int(self._seq_idx[index])]
        return seq.name, [seq.images[f].stem for f in self._snippets[index]]

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
        if self.has_pose:
            c2w = torch.from_numpy(seq.poses)
            src = [int(f) for k, f in enumerate(frames) if k != self.center]
            pose_gt = relative_pose(c2w[tgt].expand(len(src), 4, 4), c2w[src]).numpy()
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
