"""Training and evaluation samples (snippets of consecutive frames) from datasets in the cylsfm format.

A sample is a *snippet*: a target frame and ``seq_length - 1`` source frames around it, with the camera's
intrinsics at the four network scales and, where the dataset has them, ground-truth depth, relative poses
and the static mask. The keys are those of :class:`SequenceDataset`; :func:`camera_of` rebuilds the
camera of a sample or of a collated batch.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor
from torch.utils.data import Dataset

from ..geometry import Camera, relative_pose, yaw_matrix
from .format import (
    DatasetError,
    DatasetWarning,
    SequenceInfo,
    load_depth,
    load_image,
    load_mask,
    scan_dataset,
)
from .splits import SPLIT_PARTS, check_snippet_args, read_split, snippet_offsets, split_path

__all__ = [
    "NUM_SCALES",
    "AugmentConfig",
    "SequenceDataset",
    "StaticFilter",
    "camera_class",
    "camera_of",
    "intrinsics_pyramid",
]

#: Number of network scales whose intrinsics a sample carries (rows of ``"intrinsics"``).
NUM_SCALES = 4

_MIRROR = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=torch.float64))
_GREY = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
_RGB_TO_YIQ = torch.tensor(
    [[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=torch.float64
)
_YIQ_TO_RGB = torch.linalg.inv(_RGB_TO_YIQ)


# --------------------------------------------------------------------------------------- configs
@dataclass(frozen=True)
class AugmentConfig:
    """Data augmentation of training samples. Every frame of a sample gets the same transformation, so
    that view synthesis between them stays consistent; ground truth is transformed with the images.

    Attributes:
        mirror: horizontal flip of all frames with probability ``mirror_prob``. The camera becomes
            ``cx' = (W-1) - cx``, depth and mask are flipped, and ground-truth relative poses are mirrored
            ``T' = M T M`` with ``M = diag(-1, 1, 1, 1)``.
        mirror_prob: probability of a flip.
        color_jitter: random brightness, contrast, saturation and hue, the same for all frames.
        brightness: factor drawn in ``[1 - b, 1 + b]``.
        contrast: factor drawn in ``[1 - c, 1 + c]`` (about the sample's mean grey level).
        saturation: factor drawn in ``[1 - s, 1 + s]``.
        hue: rotation of the chroma (YIQ) plane by up to ``+-hue`` of a full turn.
        roll: roll all frames horizontally by a random number ``k`` of columns (uniform in ``[0, W)``):
            a yaw rotation of the camera by ``2 pi k / W``. Depth and mask are rolled, and ground-truth
            relative poses conjugated with ``yaw_matrix(2 pi k / W)``. Only for full 360° panoramas
            (cameras that wrap). **Off by default**: the paper's pose network ends in a spatial average,
            which is invariant to rolls, so it cannot predict the rotated ego-motion; in a prototype,
            rolling made ego-motion unlearnable. It is meant for a yaw-equivariant pose network.
        reverse: play the snippet backwards with probability ``reverse_prob``: the sources swap places
            (the frame after the target comes first) and so do their ground-truth poses. The target and
            its depth are unchanged. Without it every sample moves forward and the pose network can
            predict "the first source is one step back" from the source's slot alone, without reading
            the motion from the images; with it the slot says nothing.
        reverse_prob: probability of a reversal.
    """

    mirror: bool = True
    mirror_prob: float = 0.5
    color_jitter: bool = True
    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.05
    roll: bool = False
    reverse: bool = False
    reverse_prob: float = 0.5

    def __post_init__(self) -> None:
        if not 0 <= self.mirror_prob <= 1:
            raise ValueError(f"mirror_prob must be in [0, 1], got {self.mirror_prob}")
        if not 0 <= self.reverse_prob <= 1:
            raise ValueError(f"reverse_prob must be in [0, 1], got {self.reverse_prob}")
        for name in ("brightness", "contrast", "saturation"):
            value = getattr(self, name)
            if not 0 <= value <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        if not 0 <= self.hue <= 0.5:
            raise ValueError(f"hue must be in [0, 0.5] (a fraction of a turn), got {self.hue}")


@dataclass(frozen=True)
class StaticFilter:
    """Removal of frames taken while the camera stood still, before snippets are formed.

    A frame is kept when it moved enough relative to the last kept frame (the first frame is kept).

    Attributes:
        method: ``"poses"``: camera-centre distance from the ground-truth poses, at least
            ``min_translation`` metres (the paper's method); ``"image"``: mean absolute difference of
            downsampled grey frames in ``[0, 1]``, at least ``min_image_diff`` (decodes every frame once
            when the dataset is built); ``"auto"``: poses where a sequence has them, else images;
            ``"none"``: keep every frame.
        min_translation: metres between consecutive kept frames.
        min_image_diff: mean absolute grey difference between consecutive kept frames.
    """

    method: str = "auto"
    min_translation: float = 0.05
    min_image_diff: float = 0.01

    def __post_init__(self) -> None:
        if self.method not in ("auto", "poses", "image", "none"):
            raise ValueError(f"static filter method must be auto, poses, image or none, got {self.method!r}")
        if self.min_translation < 0 or self.min_image_diff < 0:
            raise ValueError("static filter thresholds must be non-negative")


# --------------------------------------------------------------------------------------- cameras
def camera_class(model: str) -> type[Camera]:
    """The :class:`~cylsfm.geometry.Camera` subclass of a model name (``"cylindrical"``, ``"pinhole"`` ...)."""
    todo = list(Camera.__subclasses__())
    known = []
    while todo:
        cls = todo.pop()
        if cls.model == model:
            return cls
        known.append(cls.model)
        todo.extend(cls.__subclasses__())
    raise ValueError(f"unknown camera model {model!r} (expected one of {sorted(m for m in known if m)})")


def _scale_size(width: int, height: int, scale: int) -> tuple[int, int]:
    f = 2**scale
    return math.ceil(width / f), math.ceil(height / f)


def intrinsics_pyramid(camera: Camera, scales: int = NUM_SCALES) -> Tensor:
    """``float32 [scales, 4]``: row ``s`` holds ``(fx, cx, fy, cy)`` (pixels) of the camera resized to
    ``(ceil(W / 2^s), ceil(H / 2^s))`` (the sizes of the network's outputs)."""
    rows = []
    for s in range(scales):
        w, h = _scale_size(camera.width, camera.height, s)
        cam = camera if s == 0 else camera.resized(w, h)
        rows.append([float(cam.fx), float(cam.cx), float(cam.fy), float(cam.cy)])
    return torch.tensor(rows, dtype=torch.float32)


def camera_of(sample: Mapping[str, Any], scale: int = 0) -> Camera:
    """The camera of a sample (scalar intrinsics) or of a collated batch (``[B]`` tensor intrinsics).

    Uses ``sample["intrinsics"]`` (``[4,4]`` or ``[B,4,4]``), ``"camera_model"`` and ``"size"``; ``scale``
    picks the network scale (image size ``(ceil(W / 2^s), ceil(H / 2^s))``). Augmented samples carry
    their augmented camera (e.g. the mirrored principal point).
    """
    intr = sample["intrinsics"]
    model = sample["camera_model"]
    size = sample["size"]
    if not 0 <= scale < intr.shape[-2]:
        raise ValueError(f"scale must be in [0, {intr.shape[-2]}), got {scale}")
    if intr.dim() == 2:
        width, height = int(size[0]), int(size[1])
        models = {model} if isinstance(model, str) else set(model)
    elif intr.dim() == 3:
        ws, hs = torch.as_tensor(size[0]).reshape(-1), torch.as_tensor(size[1]).reshape(-1)
        if bool((ws != ws[0]).any()) or bool((hs != hs[0]).any()):
            raise ValueError("a batch's samples must share one image size")
        width, height = int(ws[0]), int(hs[0])
        models = {model} if isinstance(model, str) else set(model)
    else:
        raise ValueError(f"intrinsics must be [S,4] or [B,S,4], got {tuple(intr.shape)}")
    if len(models) != 1:
        raise ValueError(f"a batch's samples must share one camera model, got {sorted(models)}")
    cls = camera_class(models.pop())
    w, h = _scale_size(width, height, scale)
    row = intr[..., scale, :]
    if intr.dim() == 2:
        fx, cx, fy, cy = (float(v) for v in row)
        return cls(width=w, height=h, fx=fx, cx=cx, fy=fy, cy=cy)
    return cls(width=w, height=h, fx=row[:, 0], cx=row[:, 1], fy=row[:, 2], cy=row[:, 3])


# --------------------------------------------------------------------------------------- samples
def _color_matrix(cfg: AugmentConfig, mean_grey: float) -> tuple[Tensor, Tensor]:
    """Random colour transform ``x -> A x + t`` (``A [3,3]``, ``t [3]``): brightness, contrast, saturation
    and hue in that order, composed into one affine map."""
    r = torch.rand(4, dtype=torch.float64) * 2 - 1
    b = 1 + cfg.brightness * float(r[0])
    c = 1 + cfg.contrast * float(r[1])
    s = 1 + cfg.saturation * float(r[2])
    angle = 2 * math.pi * cfg.hue * float(r[3])
    sat = s * torch.eye(3, dtype=torch.float64) + (1 - s) * _GREY.expand(3, 3)
    rot = torch.eye(3, dtype=torch.float64)
    rot[1:, 1:] = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    hue = _YIQ_TO_RGB @ rot @ _RGB_TO_YIQ
    a = hue @ sat * (c * b)
    # the contrast pivot is grey, which saturation and hue leave unchanged
    t = torch.full((3,), (1 - c) * b * mean_grey, dtype=torch.float64)
    return a.float(), t.float()


def _augment_geometry(
    frames: Tensor,
    camera: Camera,
    depth: Tensor | None,
    mask: Tensor | None,
    pose_gt: Tensor | None,
    cfg: AugmentConfig,
) -> tuple[Tensor, Camera, Tensor | None, Tensor | None, Tensor | None]:
    """Reverse, roll and mirror all frames ``uint8 [L,H,W,3]`` of a sample (target first, then the sources
    in time order) together, with their ground truth."""
    width = camera.width
    if cfg.reverse and float(torch.rand(())) < cfg.reverse_prob:
        frames = torch.cat([frames[:1], frames[1:].flip(0)])
        pose_gt = None if pose_gt is None else pose_gt.flip(0)
    if cfg.roll:
        k = int(torch.randint(0, width, ()))
        if k:
            frames = torch.roll(frames, k, dims=2)
            depth = None if depth is None else torch.roll(depth, k, dims=-1)
            mask = None if mask is None else torch.roll(mask, k, dims=-1)
            if pose_gt is not None:
                # the content at azimuth theta is now at theta + a: new camera points = Y @ old ones,
                # so T' = Y T Y^-1
                yaw = torch.eye(4, dtype=torch.float64)
                yaw[:3, :3] = yaw_matrix(2 * math.pi * k / width, dtype=torch.float64)
                pose_gt = yaw @ pose_gt @ yaw.T
    if cfg.mirror and float(torch.rand(())) < cfg.mirror_prob:
        frames = frames.flip(2)
        depth = None if depth is None else depth.flip(-1)
        mask = None if mask is None else mask.flip(-1)
        camera = replace(camera, cx=(camera.width - 1) - camera.cx)
        if pose_gt is not None:
            pose_gt = _MIRROR @ pose_gt @ _MIRROR
    return frames, camera, depth, mask, pose_gt


def _to_float(frames: Tensor, cfg: AugmentConfig | None) -> Tensor:
    """``uint8 [L,H,W,3]`` -> ``float32 [L,3,H,W]`` in ``[0, 1]``, colour-jittered (the same for all frames)
    when ``cfg.color_jitter``."""
    x = frames.permute(0, 3, 1, 2).to(dtype=torch.float32, memory_format=torch.contiguous_format)
    if cfg is None or not cfg.color_jitter:
        return x.div_(255.0)
    # the contrast pivot: the sample's mean grey level (a sparse grid of pixels is enough)
    mean_grey = float(x[..., ::4, ::4].mean(dim=(0, 2, 3)).double() @ _GREY) / 255.0
    a, t = _color_matrix(cfg, mean_grey)
    # x -> A x / 255 + t at every pixel: a 1x1 convolution with bias, one fused pass
    return F.conv2d(x, (a / 255.0).view(3, 3, 1, 1), t).clamp_(0, 1)


def build_sample(
    frames: np.ndarray,
    camera: Camera,
    augment: AugmentConfig | None,
    *,
    sequence: str,
    frame: str,
    index: int,
    depth: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    pose_gt: np.ndarray | None = None,
) -> dict[str, Any]:
    """Assemble (and augment) a sample from decoded frames.

    Args:
        frames: ``uint8 [L,H,W,3]``, the snippet in time order; the target is the middle one.
        camera: the camera of the frames (size ``W x H``).
        augment: augmentation, or ``None``.
        sequence, frame, index: the sample's origin.
        depth: target depth ``float32 [H,W]`` (metres, 0 = unknown), or ``None``.
        mask: ``float32 [H,W]`` in ``{0, 1}``, or ``None``.
        pose_gt: ``float64 [L-1,4,4]`` ``T_tgt_to_src`` per source, or ``None``.

    Returns:
        The sample dictionary (keys documented in :class:`SequenceDataset`).
    """
    n = frames.shape[0]
    t = n // 2
    # target first, then the sources in time order: one conversion, and target / sources are views
    order = [t, *range(t), *range(t + 1, n)]
    frames_t = torch.from_numpy(np.ascontiguousarray(frames[order]))
    depth_t = None if depth is None else torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None]
    mask_t = None if mask is None else torch.from_numpy(np.ascontiguousarray(mask, dtype=np.float32))[None]
    pose_t = None if pose_gt is None else torch.as_tensor(pose_gt, dtype=torch.float64)
    if augment is not None:
        frames_t, camera, depth_t, mask_t, pose_t = _augment_geometry(
            frames_t, camera, depth_t, mask_t, pose_t, augment
        )
    images = _to_float(frames_t, augment)
    sample: dict[str, Any] = {
        "target": images[0],
        "sources": images[1:],
        "intrinsics": intrinsics_pyramid(camera),
        "camera_model": camera.model,
        "size": camera.size,
    }
    if depth_t is not None:
        sample["depth"] = depth_t.contiguous()
    if pose_t is not None:
        sample["pose_gt"] = pose_t.float()
    if mask_t is not None:
        sample["mask"] = mask_t.contiguous()
    sample["sequence"] = sequence
    sample["frame"] = frame
    sample["index"] = index
    return sample


# --------------------------------------------------------------------------------------- static frames
_THUMB_WIDTH = 64


def _grey_thumbnail(path: Path) -> np.ndarray:
    """``float32 [h, 64]`` grey version of an image in ``[0, 1]`` (area downsampled)."""
    try:
        with Image.open(path) as im:
            w, h = im.size
            tw = min(_THUMB_WIDTH, w)
            th = max(1, round(h * tw / w))
            im.draft("L", (tw, th))
            grey = im.convert("L").resize((tw, th), Image.Resampling.BOX)
            return np.asarray(grey, dtype=np.float32) / 255.0
    except Exception as exc:
        raise DatasetError(f"{path}: cannot decode image ({exc or type(exc).__name__})") from None


def _keep_moving(distance, count: int, threshold: float) -> list[int]:
    """Positions kept when each must be at least ``threshold`` away (``distance(i, j)``) from the last kept."""
    kept = [0] if count else []
    for i in range(1, count):
        if distance(kept[-1], i) >= threshold:
            kept.append(i)
    return kept


def _runs(n: int, bad: set[int]) -> list[list[int]]:
    """Maximal runs of consecutive good frames."""
    runs: list[list[int]] = []
    current: list[int] = []
    for i in range(n):
        if i in bad:
            if current:
                runs.append(current)
            current = []
        else:
            current.append(i)
    if current:
        runs.append(current)
    return runs


# --------------------------------------------------------------------------------------- dataset
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

    Raises:
        DatasetError: naming the file, for any invalid input (see :func:`scan_dataset`); at load time for a
            corrupt image or depth map (unless ``skip_bad``).
        ValueError: for invalid arguments (even ``seq_length``, ``roll`` on a camera that does not wrap).
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
    ) -> None:
        check_snippet_args(seq_length, stride)
        if size is not None:
            if len(size) != 2 or any(int(v) != v or v < 1 for v in size):
                raise ValueError(f"size must be (W, H) with positive integers, got {size!r}")
            size = (int(size[0]), int(size[1]))
        self.root = Path(root)
        self.seq_length = seq_length
        self.stride = stride
        self.size = size
        self.augment = augment
        self.static = static if static is not None else StaticFilter(method="none")
        self.skip_bad = skip_bad
        self.load_ground_truth = load_ground_truth
        self.sequences: list[SequenceInfo] = scan_dataset(self.root, skip_bad=skip_bad)

        sizes = {s.camera.size for s in self.sequences}
        if size is None and len(sizes) > 1:
            detail = ", ".join(f"{s.name}: {s.camera.width}x{s.camera.height}" for s in self.sequences)
            raise DatasetError(f"{self.root}: sequences differ in image size ({detail}); pass size=(W, H)")
        self.cameras: list[Camera] = [
            s.camera if size is None or s.camera.size == size else s.camera.resized(*size)
            for s in self.sequences
        ]

        # snippets over the frames left after bad-frame and static-frame removal
        offsets = snippet_offsets(seq_length, stride)  # positions in the list of kept frames
        reach = int(offsets[-1])
        tables: list[np.ndarray] = [np.zeros((0, seq_length), dtype=np.int64)]
        owners: list[np.ndarray] = [np.zeros(0, dtype=np.int64)]
        for s, seq in enumerate(self.sequences):
            for kept in self._kept_runs(seq):
                if len(kept) <= 2 * reach:
                    continue
                pos = np.arange(reach, len(kept) - reach)[:, None] + offsets[None, :]
                tables.append(np.asarray(kept, dtype=np.int64)[pos])
                owners.append(np.full(len(pos), s, dtype=np.int64))
        table = np.concatenate(tables)
        seq_arr = np.concatenate(owners)

        if split is not None:
            if isinstance(split, str) and split in SPLIT_PARTS:
                path = split_path(self.root, split, split_name)
                if not path.exists():
                    raise DatasetError(
                        f"{path}: split file not found (write it with cylsfm.data.make_splits)"
                    )
            else:
                path = Path(split)
            entries = read_split(path, self.root, self.sequences)
            seq_of_name = {seq.name: i for i, seq in enumerate(self.sequences)}
            frame_of = [{stem: i for i, stem in enumerate(seq.stems)} for seq in self.sequences]
            centres = table[:, seq_length // 2]
            where = {
                (s, f): n for n, (s, f) in enumerate(zip(seq_arr.tolist(), centres.tolist(), strict=True))
            }
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
                    f"(seq_length={seq_length}, stride={stride}, static={self.static.method}) and are skipped",
                    DatasetWarning,
                    stacklevel=2,
                )
            idx = np.asarray(chosen, dtype=np.int64)
            table, seq_arr = table[idx] if len(idx) else table[:0], seq_arr[idx]

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
        used = [self.sequences[s] for s in sorted(set(seq_arr.tolist()))]
        self.has_depth = load_ground_truth and any(s.depths is not None for s in used)
        self.has_pose = load_ground_truth and bool(used) and all(s.poses is not None for s in used)
        self.has_mask = any(s.mask is not None for s in used)
        if augment is not None and augment.roll:
            for s in sorted(set(seq_arr.tolist())):
                if not self.cameras[s].wraps:
                    raise ValueError(
                        f"roll augmentation needs full 360-degree panoramas (fx * 2 pi == width); the camera "
                        f"of sequence {self.sequences[s].name} does not wrap"
                    )
        # found at load time (per process): frames that fail to decode ((seq, -1): the mask), and
        # targets whose depth map is bad
        self._bad_frames: set[tuple[int, int]] = set()
        self._bad_targets: set[tuple[int, int]] = set()
        self._mask_cache: dict[int, np.ndarray] = {}

    # ------------------------------------------------------------------ building
    def _kept_runs(self, seq: SequenceInfo) -> list[list[int]]:
        """Runs of good frames of ``seq`` with static frames removed (updates ``seq.bad`` on decode errors)."""
        method = self.static.method
        if method == "auto":
            method = "poses" if seq.poses is not None else "image"
        if method == "poses" and seq.poses is None:
            raise DatasetError(
                f"{seq.path / 'poses.txt'}: not found (static filter 'poses' needs ground-truth poses)"
            )
        thumbs: dict[int, np.ndarray] = {}
        if method == "image":
            todo = [i for i in range(len(seq)) if i not in seq.bad]
            with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
                results = list(pool.map(_try_thumbnail, [seq.images[i] for i in todo]))
            for i, res in zip(todo, results, strict=True):
                if isinstance(res, DatasetError):
                    if not self.skip_bad:
                        raise res
                    warnings.warn(f"{res}; frame skipped", DatasetWarning, stacklevel=3)
                    seq.bad[i] = str(res)
                else:
                    thumbs[i] = res
        runs = _runs(len(seq), set(seq.bad))
        if method == "none":
            return runs
        out = []
        for run in runs:
            if method == "poses":
                centres = seq.poses[run, :3, 3]
                pos = _keep_moving(
                    lambda a, b, c=centres: float(np.linalg.norm(c[b] - c[a])),
                    len(run),
                    self.static.min_translation,
                )
            else:
                th = [thumbs[i] for i in run]
                pos = _keep_moving(
                    lambda a, b, th=th: float(np.abs(th[b] - th[a]).mean()),
                    len(run),
                    self.static.min_image_diff,
                )
            out.append([run[p] for p in pos])
        return out

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
                images.append(load_image(seq.images[f], size))
            except DatasetError:
                self._bad_frames.add((s, f))
                raise
        tgt = int(frames[self.center])
        depth = None
        if self.has_depth:
            path = seq.depth_path(tgt)
            if path is None:
                depth = np.zeros((camera.height, camera.width), dtype=np.float32)
            else:
                try:
                    depth = load_depth(path, size)
                except DatasetError:
                    self._bad_targets.add((s, tgt))
                    raise
        mask = None
        if self.has_mask:
            mask = self._mask_cache.get(s)
            if mask is None:
                if seq.mask is None:
                    mask = np.ones((camera.height, camera.width), dtype=np.float32)
                else:
                    try:
                        mask = load_mask(seq.mask, size)
                    except DatasetError:
                        self._bad_frames.add((s, -1))
                        raise
                self._mask_cache[s] = mask
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


def _try_thumbnail(path: Path) -> np.ndarray | DatasetError:
    try:
        return _grey_thumbnail(path)
    except DatasetError as exc:
        return exc
