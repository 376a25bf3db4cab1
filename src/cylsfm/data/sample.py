"""A training or evaluation sample: its tensors and its camera at the network's scales.

A sample is a *snippet*: a target frame and ``seq_length - 1`` source frames around it, with the camera's
intrinsics at the :data:`NUM_SCALES` network scales and, where the dataset has them, ground-truth depth,
relative poses and the static mask. :func:`build_sample` assembles (and augments) one from decoded frames;
its keys are documented in :class:`~cylsfm.data.SequenceDataset`. :func:`camera_of` rebuilds the camera
of a sample or of a collated batch.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError
from ..geometry import Camera
from .augment import AugmentConfig, augment_geometry, to_float

__all__ = ["NUM_SCALES", "build_sample", "camera_class", "camera_of", "check_size", "intrinsics_pyramid"]

#: Number of network scales whose intrinsics a sample carries (rows of ``"intrinsics"``).
NUM_SCALES = 4


def check_size(size: tuple[int, int] | None) -> tuple[int, int] | None:
    """``size = (W, H)`` to resample frames to as two ints, or ``None``; InputError unless positive integers."""
    if size is None:
        return None
    if len(size) != 2 or any(int(v) != v or v < 1 for v in size):
        raise InputError(f"size must be (W, H) with positive integers, got {size!r}")
    return int(size[0]), int(size[1])


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
    raise InputError(f"unknown camera model {model!r} (expected one of {sorted(m for m in known if m)})")


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

    Raises:
        InputError: for a scale out of range, intrinsics of another shape, or a batch whose samples
            differ in image size or camera model.
    """
    intr = sample["intrinsics"]
    model = sample["camera_model"]
    size = sample["size"]
    if not 0 <= scale < intr.shape[-2]:
        raise InputError(f"scale must be in [0, {intr.shape[-2]}), got {scale}")
    if intr.dim() == 2:
        width, height = int(size[0]), int(size[1])
    elif intr.dim() == 3:
        ws, hs = torch.as_tensor(size[0]).reshape(-1), torch.as_tensor(size[1]).reshape(-1)
        if bool((ws != ws[0]).any()) or bool((hs != hs[0]).any()):
            raise InputError("a batch's samples must share one image size")
        width, height = int(ws[0]), int(hs[0])
    else:
        raise InputError(f"intrinsics must be [S,4] or [B,S,4], got {tuple(intr.shape)}")
    models = {model} if isinstance(model, str) else set(model)
    if len(models) != 1:
        raise InputError(f"a batch's samples must share one camera model, got {sorted(models)}")
    cls = camera_class(models.pop())
    w, h = _scale_size(width, height, scale)
    row = intr[..., scale, :]
    if intr.dim() == 2:
        fx, cx, fy, cy = (float(v) for v in row)
        return cls(width=w, height=h, fx=fx, cx=cx, fy=fy, cy=cy)
    return cls(width=w, height=h, fx=row[:, 0], cx=row[:, 1], fy=row[:, 2], cy=row[:, 3])


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
    sfm: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
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
        sfm: the ride's own geometry, or ``None``: ``(depth [4,H,W], T_tgt_to_src [L-1,4,4], step [L-1])``
            (:meth:`~cylsfm.data.geometry.RideGeometry.depth_map`, ``relative``); augmented with the rest.

    Returns:
        The sample dictionary (keys documented in :class:`~cylsfm.data.SequenceDataset`).
    """
    n = frames.shape[0]
    t = n // 2
    # target first, then the sources in time order: one conversion, and target / sources are views
    order = [t, *range(t), *range(t + 1, n)]
    frames_t = torch.from_numpy(np.ascontiguousarray(frames[order]))
    depth_t = None if depth is None else torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None]
    mask_t = None if mask is None else torch.from_numpy(np.ascontiguousarray(mask, dtype=np.float32))[None]
    pose_t = None if pose_gt is None else torch.as_tensor(pose_gt, dtype=torch.float64)
    maps = [depth_t, None if sfm is None else torch.as_tensor(sfm[0], dtype=torch.float32)]
    poses = [pose_t, None if sfm is None else torch.as_tensor(sfm[1], dtype=torch.float64)]
    if augment is not None:
        frames_t, camera, mask_t, maps, poses = _augmented(frames_t, camera, mask_t, maps, poses, augment)
    (depth_t, sfm_depth), (pose_t, sfm_pose) = maps, poses
    images = to_float(frames_t, augment)
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
    if sfm_depth is not None:
        sample["sfm_depth"] = sfm_depth.contiguous()
        sample["sfm_pose"] = sfm_pose.float()
        sample["sfm_step"] = torch.as_tensor(sfm[2], dtype=torch.float32)  # type: ignore[index]
    sample["sequence"] = sequence
    sample["frame"] = frame
    sample["index"] = index
    return sample


def _augmented(
    frames: Tensor,
    camera: Camera,
    mask: Tensor | None,
    maps: list[Tensor | None],
    poses: list[Tensor | None],
    augment: AugmentConfig,
) -> tuple[Tensor, Camera, Tensor | None, list[Tensor | None], list[Tensor | None]]:
    """:func:`augment_geometry` of the frames with several target maps ``[C,H,W]`` (ground truth, the ride's
    own geometry) and pose stacks ``[K,4,4]`` at once (one draw for all; ``None`` entries kept)."""
    have_m, have_p = [m for m in maps if m is not None], [p for p in poses if p is not None]
    frames, camera, m, mask, p = augment_geometry(
        frames,
        camera,
        torch.cat(have_m) if have_m else None,
        mask,
        torch.cat(have_p) if have_p else None,
        augment,
    )
    pieces_m = iter(m.split([len(x) for x in have_m])) if m is not None else iter(())
    pieces_p = iter(p.split([len(x) for x in have_p])) if p is not None else iter(())
    return (
        frames,
        camera,
        mask,
        [None if x is None else next(pieces_m) for x in maps],
        [None if x is None else next(pieces_p) for x in poses],
    )
