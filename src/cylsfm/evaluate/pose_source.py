"""Where the estimated trajectories of :mod:`cylsfm.evaluate.pose` come from: the pose network run over a
chain of frames, or the TUM files of another method matched to the ground truth by timestamp.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data import DatasetError, SequenceInfo, read_tum
from ..runtime import progress_bar
from .frames import load_images, prefetch
from .pose_metrics import consecutive_from_windows, match_times

__all__ = ["predict_consecutive", "read_matched", "trajectory_file"]


def predict_consecutive(
    predictor: Any,
    images: Sequence[Path],
    camera: Any,
    batch_size: int = 8,
    progress: bool | None = False,
    desc: str = "poses",
    roll: int = 0,
) -> np.ndarray:
    """Run the pose network over a chain of frames and return ``T_{j->j+1}`` ``[M-1,4,4]`` (float64).

    Args:
        predictor: a :class:`cylsfm.model.Predictor` (``.poses``, ``.config.data.seq_length``).
        images: the chain's image files in time order (``M >= seq_length``).
        camera: their camera.
        batch_size: windows per network call.
        progress: show a progress bar labelled ``desc`` (``None``: when stderr is a terminal).
        roll: roll every frame horizontally by this many columns first (a yaw of the camera).
    """
    seq_length = int(predictor.config.data.seq_length)
    k = (seq_length - 1) // 2
    m = len(images)
    centres = list(range(k, m - k))
    chunks = [centres[i : i + batch_size] for i in range(0, len(centres), batch_size)]
    windows: dict[int, np.ndarray] = {}
    bar = progress_bar(total=len(centres), desc=desc, enabled=progress)
    with ThreadPoolExecutor(max_workers=2) as pool:
        # the frames of a chunk: chain frames chunk[0] - k .. chunk[-1] + k
        load = [[images[f] for f in range(c[0] - k, c[-1] + k + 1)] for c in chunks]
        for chunk, frames in zip(
            chunks, prefetch(pool, lambda p: load_images(p, roll), load, 2), strict=True
        ):
            # frames[i] is chain frame chunk[0] - k + i; the window of centre c is frames[c - chunk[0] + ...]
            idx = torch.tensor([[c - chunk[0] + o for o in range(2 * k + 1)] for c in chunk])
            win = frames[idx]  # [B, L, 3, H, W]
            src = torch.cat((win[:, :k], win[:, k + 1 :]), 1)
            rel = predictor.poses(win[:, k], src, camera).double().cpu().numpy()
            for c, r in zip(chunk, rel, strict=True):
                windows[c] = r
            bar.update(len(chunk))
    bar.close()
    return consecutive_from_windows(windows, m, seq_length)


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
