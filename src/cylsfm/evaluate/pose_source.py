"""Where the estimated trajectories of :mod:`cylsfm.evaluate.pose` come from: the pose network run over a
chain of frames (with the probes of :mod:`cylsfm.evaluate.motion`), the visual compass, or the TUM files of
another method matched to the ground truth by timestamp.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data import DatasetError, SequenceInfo, read_tum
from ..geometry import compass_yaw, roll_angle, roll_columns, rotation_y
from ..runtime import progress_bar
from .frames import load_images, prefetch
from .pose_metrics import consecutive_from_windows, match_times

__all__ = [
    "WindowPoses",
    "compass_steps",
    "predict_consecutive",
    "predict_windows",
    "read_matched",
    "trajectory_file",
]


@dataclass
class WindowPoses:
    """The pose network's predictions over a chain of ``M`` frames, window by window.

    Each dict maps the chain index ``c`` of a window's centre (target) to ``T_{c->src}`` ``[L-1,4,4]``
    (float64) for its sources in time order (frames ``c-k .. c+k`` without ``c``): ``real`` for the real
    window, ``standing`` with every source replaced by the target (a camera standing still: the true motion
    is zero), ``swapped`` with the sources given in reverse order (the predictions put back in time order,
    so that ``swapped[c][i]`` and ``real[c][i]`` are about the same image).
    """

    seq_length: int
    real: dict[int, np.ndarray] = field(default_factory=dict)
    standing: dict[int, np.ndarray] = field(default_factory=dict)
    swapped: dict[int, np.ndarray] = field(default_factory=dict)

    def steps(self, m: int) -> np.ndarray:
        """Consecutive relative poses ``T_{j->j+1}`` ``[M-1,4,4]`` (:func:`consecutive_from_windows`)."""
        return consecutive_from_windows(self.real, m, self.seq_length)

    def forward_backward_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """``(T_{c->c+1}, T_{c+1->c})`` ``[N,4,4]`` each: the first from the window centred on ``c``, the
        second from the one centred on ``c + 1``, for every pair of consecutive full windows."""
        k = (self.seq_length - 1) // 2
        pairs = [(self.real[c][k], self.real[c + 1][k - 1]) for c in sorted(self.real) if c + 1 in self.real]
        if not pairs:
            return np.zeros((0, 4, 4)), np.zeros((0, 4, 4))
        ab, ba = zip(*pairs, strict=True)
        return np.stack(ab), np.stack(ba)


def predict_windows(
    predictor: Any,
    images: Sequence[Path],
    camera: Any,
    batch_size: int = 8,
    progress: bool | None = False,
    desc: str = "poses",
    roll: int = 0,
    probes: bool = True,
    mask: np.ndarray | None = None,
) -> WindowPoses:
    """Run the pose network on every full window of a chain of frames (see :class:`WindowPoses`).

    Args:
        predictor: a :class:`cylsfm.model.Predictor` (``.poses``, ``.window_length``).
        images: the chain's image files in time order (``M >= seq_length``).
        camera: their camera.
        batch_size: windows per network call.
        progress: show a progress bar labelled ``desc`` (``None``: when stderr is a terminal).
        roll: roll every frame horizontally by this many columns first (a yaw of the camera).
        probes: also predict each window standing still and with its sources swapped (two more runs).
        mask: ``[H,W]`` 1 where the frames see the scene, 0 on an occluder fixed to the camera (the
            sequence's ``mask.png``), which the network sees filled; rolled with the frames.
    """
    masked = {"mask": _mask_tensor(mask, roll)} if mask is not None else {}
    seq_length = int(predictor.window_length)
    k = (seq_length - 1) // 2
    centres = list(range(k, len(images) - k))
    chunks = [centres[i : i + batch_size] for i in range(0, len(centres), batch_size)]
    out = WindowPoses(seq_length)
    bar = progress_bar(total=len(centres), desc=desc, enabled=progress)
    with ThreadPoolExecutor(max_workers=2) as pool:
        # the frames of a chunk: chain frames chunk[0] - k .. chunk[-1] + k
        load = [[images[f] for f in range(c[0] - k, c[-1] + k + 1)] for c in chunks]
        for chunk, frames in zip(
            chunks, prefetch(pool, lambda p: load_images(p, roll), load, 2), strict=True
        ):
            # frames[i] is chain frame chunk[0] - k + i
            idx = torch.tensor([[c - chunk[0] + o for o in range(2 * k + 1)] for c in chunk])
            win = frames[idx]  # [B, L, 3, H, W]
            tgt, src = win[:, k], torch.cat((win[:, :k], win[:, k + 1 :]), 1)
            runs = {"real": src}
            if probes:
                runs["standing"] = tgt[:, None].expand_as(src).contiguous()
                runs["swapped"] = src.flip(1)
            for name, sources in runs.items():
                rel = predictor.poses(tgt, sources, camera, **masked).double().cpu().numpy()
                if name == "swapped":
                    rel = rel[:, ::-1]
                store = getattr(out, name)
                for c, r in zip(chunk, rel, strict=True):
                    store[c] = np.ascontiguousarray(r)
            bar.update(len(chunk))
    bar.close()
    return out


def predict_consecutive(
    predictor: Any,
    images: Sequence[Path],
    camera: Any,
    batch_size: int = 8,
    progress: bool | None = False,
    desc: str = "poses",
    roll: int = 0,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Run the pose network over a chain of frames and return ``T_{j->j+1}`` ``[M-1,4,4]`` (float64)
    (arguments as :func:`predict_windows`)."""
    windows = predict_windows(
        predictor, images, camera, batch_size, progress, desc, roll, probes=False, mask=mask
    )
    return windows.steps(len(images))


def _mask_tensor(mask: np.ndarray | None, roll: int) -> torch.Tensor | None:
    """``[H,W]`` -> ``[1,1,H,W]`` float, rolled by ``roll`` columns like the frames (``None`` stays)."""
    if mask is None:
        return None
    rolled = roll_columns(np.asarray(mask, np.float32), roll, axis=1)
    return torch.from_numpy(np.ascontiguousarray(rolled))[None, None]


def compass_steps(
    images: Sequence[Path],
    roll: int = 0,
    batch_size: int = 32,
    width: int = 0,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """The visual compass's consecutive relative poses ``T_{j->j+1}`` ``[M-1,4,4]`` (float64) of a chain
    of full panoramas: the yaw between the frames (:func:`cylsfm.geometry.compass_yaw`, no depth, nothing
    learned) after one unit step forward along the camera's +z axis (a constant speed: the scale is fitted
    by every measure that uses it). With ``roll`` (columns of ``width``: frames rolled as if the camera had
    been mounted turned) forward is +z turned by the roll. ``mask`` (``[H,W]``, as for
    :func:`predict_windows`): the occluder fixed to the camera is left out."""
    mask_t = _mask_tensor(mask, roll)
    yaws = []
    for i in range(0, len(images) - 1, batch_size):
        frames = load_images(images[i : i + batch_size + 1], roll)
        yaws.append(compass_yaw(frames[:-1], frames[1:], mask_t).numpy())
    yaw = np.concatenate(yaws) if yaws else np.zeros(0)
    out = np.tile(np.eye(4), (len(yaw), 1, 1))
    out[:, :3, :3] = rotation_y(yaw)
    ahead = np.array([0.0, 0.0, 1.0])
    if roll:
        ahead = rotation_y(np.asarray(roll_angle(roll, width))) @ ahead
    out[:, :3, 3] = -out[:, :3, :3] @ ahead  # p_b = R (p_a - c), c = the step ahead: t = -R c
    return out


def trajectory_file(path: Path, seq: SequenceInfo, n_sequences: int) -> Path:
    """The TUM file of ``seq`` in ``path`` (a directory with ``SEQ.txt``, or the file of the only sequence)."""
    if path.is_dir():
        f = path / f"{seq.name}.txt"
        if not f.is_file():
            raise DatasetError(f"{f}: trajectory not found")
        return f
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file or directory not found")
    if n_sequences != 1:
        raise DatasetError(
            f"{path}: one trajectory file for {n_sequences} sequences; give a directory with SEQ.txt per sequence"
        )
    return path


def read_matched(path: Path, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The poses of a TUM file at ``times [M]`` (nearest, within half the smallest gap between them):
    ``(c2w [M,4,4], matched bool [M])``, identity where nothing matched."""
    t_est, c2w_est = read_tum(path)
    gaps = np.diff(times)
    tol = 0.5 * float(gaps[gaps > 0].min()) if (gaps > 0).any() else 1e-3
    which = match_times(times, t_est, tol)
    matched = which >= 0
    est = np.tile(np.eye(4), (len(times), 1, 1))
    est[matched] = c2w_est[which[matched]]
    return est, matched
