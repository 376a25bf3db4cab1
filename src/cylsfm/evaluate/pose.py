"""Ego-motion evaluation: SfMLearner's snippet ATE and full-trajectory APE / RPE (with ``evo``), and baselines.

**Frames.** With a model trained with frame stride ``s`` the evaluation uses every ``s``-th frame of a
sequence (frames ``0, s, 2s, ...``, the *chain*); consecutive chain frames are one network step apart.
Evaluated sequences are those with at least one target in the split file (all of their frames, not just
the listed targets), or every sequence when ``split`` is ``None``.

**Trajectories from the pose network.** The network sees ``L = seq_length`` frames (usually 3) with the
centre one as target and predicts ``T_tgt_to_src`` for each source. It is run once on the window centred
on every chain frame ``c`` that has a full window (``k <= c <= M-1-k``, ``k = (L-1)//2``). The motion
between consecutive frames is taken from the window centred on the earlier frame, ``c = j``:
``T_{j->j+1}`` is its prediction for the source ``j+1``. Near the ends, where that window does not exist,
the nearest full window ``c = clamp(j, k, M-1-k)`` (which holds both frames) is used:
``T_{j->j+1} = T_{c->j+1} @ inv(T_{c->j})`` (with ``T_{c->c} = I``); e.g. for ``L = 3`` the first step is
``inv(T_{1->0})``. The steps are chained into camera-to-world poses, ``c2w_0 = I``,
``c2w_{j+1} = c2w_j @ inv(T_{j->j+1})`` (:func:`chain_poses`), in the network's (unknown) units.

**Snippet ATE** (SfMLearner, Zhou et al. 2017): for every run of ``snippet`` (default 5) consecutive chain
frames (overlapping: one snippet starts at every frame), both trajectories are expressed relative to the
snippet's first frame (positions of ``inv(c2w_0) @ c2w_i``), one scale ``s = sum(gt . pred) / sum(pred .
pred)`` is fitted, and ``ATE = sqrt(sum_i ||gt_i - s pred_i||^2) / N``. Note the division of the *root* of
the summed squared error by ``N`` (not a root mean square): that is what SfMLearner's published
evaluation code computes, and it reproduces the paper's numbers. Mean and standard deviation over all
snippets of all evaluated sequences: ``ate_mean``, ``ate_std`` (metres). Predicted snippets are cut from
the chained trajectory, which is the same as chaining the snippet's own consecutive steps.

**Full trajectories** (``evo``): the chained trajectory is compared with ``poses.txt`` by ``evo``'s APE
(translation part) after a Sim(3) Umeyama alignment (``align(correct_scale=True)`` on a copy) and RPE
between consecutive chain frames (translation, on the aligned copy, so in metres; and rotation angle in
degrees). Per-sequence numbers are averaged over sequences (each sequence weighs the same).

**Baselines**, on the same snippets and frames:

- *zero motion*: the camera never moves. Snippet ATE with a zero prediction (the fitted scale is 0). A
  single point cannot be Sim(3)-aligned (Umeyama needs non-collinear points), so its full-trajectory APE is
  that of a camera standing at the ground truth's centroid (the best any alignment of one point can do);
  no RPE.
- *constant velocity*: the same step every frame along the camera's +z axis, no rotation; scale fitted per
  snippet like a prediction. For full trajectories its best Sim(3) alignment is computed in closed form:
  ``s R (0, 0, i) + t = i v + t`` for any vector ``v``, so the aligned positions are the least-squares line
  ``c + v i`` through the ground-truth positions (``evo``'s Umeyama refuses collinear points); ``evo``
  then computes APE and RPE on that aligned trajectory.

**Other methods** (``trajectory=``): TUM files (camera-to-world) of any method are scored the same way.
Their poses are matched to the ground truth of the chain frames by timestamp (nearest, within half the
smallest gap between ground-truth timestamps): write timestamps equal to those of the dataset's
``poses.txt`` (the trajectories this module writes do). Snippets are cut from the matched poses (a snippet
with an unmatched frame is skipped); full-trajectory metrics use the matched poses.
"""

from __future__ import annotations

import copy
import io
import math
import os
import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.format import (
    DatasetError,
    DatasetWarning,
    SequenceInfo,
    atomic_write_bytes,
    load_image,
    read_tum,
    scan_dataset,
    write_tum,
)
from .depth import _prefetch, _progress, _to_tensor, split_entries

__all__ = [
    "ate_positions",
    "chain_poses",
    "consecutive_from_windows",
    "constant_velocity_trajectory",
    "evaluate_pose",
    "format_pose_table",
    "plot_trajectories",
    "pose_json",
    "predict_consecutive",
    "relative_positions",
    "snippet_ate",
    "snippet_ates",
    "trajectory_metrics",
]

PathLike = str | os.PathLike[str]

#: Full-trajectory measures (metres, degrees) reported per sequence and averaged.
TRAJECTORY_METRICS = ("ape_rmse", "ape_mean", "ape_median", "ape_max", "rpe_trans_rmse", "rpe_rot_deg_rmse")


# --------------------------------------------------------------------------------------- snippet ATE
def relative_positions(c2w: np.ndarray) -> np.ndarray:
    """Camera centres ``[N,3]`` of camera-to-world poses ``c2w [N,4,4]`` in the first camera's frame
    (the positions of ``inv(c2w_0) @ c2w_i``; the first is 0)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    rot0, t0 = c2w[0, :3, :3], c2w[0, :3, 3]
    return (c2w[:, :3, 3] - t0) @ rot0  # R0^T (t_i - t0), row-wise


def ate_positions(gt: np.ndarray, pred: np.ndarray) -> float:
    """SfMLearner's ATE of positions already expressed in the snippet's first frame.

    Args:
        gt: ground-truth positions ``[N,3]`` (metres).
        pred: predicted positions ``[N,3]`` (any units).

    Returns:
        ``sqrt(sum_i ||gt_i - s pred_i||^2) / N`` with the least-squares scale
        ``s = sum(gt . pred) / sum(pred . pred)`` (``s = 0`` for an all-zero prediction), in metres.
    """
    g = np.asarray(gt, dtype=np.float64)
    p = np.asarray(pred, dtype=np.float64)
    if g.shape != p.shape or g.ndim != 2 or g.shape[1] != 3 or g.shape[0] == 0:
        raise ValueError(f"gt and pred must both be [N,3] with N >= 1, got {g.shape} and {p.shape}")
    den = float(np.sum(p * p))
    s = float(np.sum(g * p)) / den if den > 0 else 0.0
    return float(np.sqrt(np.sum((g - s * p) ** 2)) / g.shape[0])


def snippet_ate(gt_c2w: np.ndarray, pred_c2w: np.ndarray) -> float:
    """ATE of one snippet of camera-to-world poses ``[N,4,4]`` (ground truth in metres, prediction in any
    units): both made relative to their first frame, then :func:`ate_positions`."""
    return ate_positions(relative_positions(gt_c2w), relative_positions(pred_c2w))


def constant_velocity_trajectory(n: int, step: float = 1.0) -> np.ndarray:
    """``[n,4,4]`` camera-to-world poses moving ``step`` along +z every frame, no rotation."""
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, 2, 3] = step * np.arange(n)
    return out


def snippet_ates(
    gt_c2w: np.ndarray,
    pred_c2w: np.ndarray | None,
    snippet: int = 5,
    matched: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Snippet ATEs of one sequence for the prediction and both baselines.

    Args:
        gt_c2w: ground truth ``[M,4,4]`` of the chain frames (metres).
        pred_c2w: prediction ``[M,4,4]`` (rows of unmatched frames are ignored), or ``None``.
        snippet: frames per snippet; one snippet starts at every frame ``0 .. M - snippet``.
        matched: bool ``[M]``, frames that have a prediction (default: all); snippets with an unmatched
            frame are skipped for the prediction and the baselines alike.

    Returns:
        ``{"model": [n], "zero_motion": [n], "constant_velocity": [n]}`` (``"model"`` absent without a
        prediction), ``n`` the number of usable snippets.
    """
    if snippet < 2:
        raise ValueError(f"snippet must be at least 2 frames, got {snippet}")
    m = len(gt_c2w)
    ok = np.ones(m, dtype=bool) if matched is None else np.asarray(matched, dtype=bool)
    cv = relative_positions(constant_velocity_trajectory(snippet))
    zero = np.zeros((snippet, 3))
    out: dict[str, list[float]] = {"zero_motion": [], "constant_velocity": []}
    if pred_c2w is not None:
        out["model"] = []
    for j in range(m - snippet + 1):
        if not ok[j : j + snippet].all():
            continue
        g = relative_positions(gt_c2w[j : j + snippet])
        out["zero_motion"].append(ate_positions(g, zero))
        out["constant_velocity"].append(ate_positions(g, cv))
        if pred_c2w is not None:
            out["model"].append(ate_positions(g, relative_positions(pred_c2w[j : j + snippet])))
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


# --------------------------------------------------------------------------------------- chaining
def _inv(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def chain_poses(steps: np.ndarray) -> np.ndarray:
    """Camera-to-world poses ``[M,4,4]`` (first = identity) from consecutive relative poses
    ``steps [M-1,4,4]`` = ``T_{j->j+1}`` (target ``j``, source ``j+1``: ``p_{j+1} = T p_j``):
    ``c2w_{j+1} = c2w_j @ inv(T_{j->j+1})``."""
    steps = np.asarray(steps, dtype=np.float64)
    out = np.tile(np.eye(4), (len(steps) + 1, 1, 1))
    for j, t in enumerate(steps):
        out[j + 1] = out[j] @ _inv(t)
    return out


def _window_centre(j: int, m: int, k: int) -> int:
    return min(max(j, k), m - 1 - k)


def consecutive_from_windows(windows: dict[int, np.ndarray], m: int, seq_length: int) -> np.ndarray:
    """Consecutive relative poses ``T_{j->j+1}`` ``[M-1,4,4]`` from the network's windows.

    Args:
        windows: ``c -> [L-1,4,4]``: ``T_{c->src}`` for the window centred on chain frame ``c``, sources in
            time order (frames ``c-k .. c+k`` without ``c``), for every ``c`` in ``k .. M-1-k``.
        m: number of chain frames ``M`` (at least ``L``).
        seq_length: ``L``, odd.

    Returns:
        ``T_{j->j+1}`` from the window centred on ``j``, or on the nearest full window near the ends
        (see the module docstring).
    """
    k = (seq_length - 1) // 2
    if m < seq_length:
        raise ValueError(f"{m} frames are fewer than one window of {seq_length}")
    eye = np.eye(4)

    def t_from(c: int, f: int) -> np.ndarray:  # T_{c->f}
        if f == c:
            return eye
        o = f - c
        return np.asarray(windows[c][o + k if o < 0 else o + k - 1], dtype=np.float64)

    out = np.empty((m - 1, 4, 4))
    for j in range(m - 1):
        c = _window_centre(j, m, k)
        out[j] = t_from(c, j + 1) @ _inv(t_from(c, j))
    return out


def _yaw4(angle: float) -> np.ndarray:
    """4x4 rotation about the vertical axis that increases azimuths by ``angle`` (``yaw_matrix``)."""
    c, s_ = np.cos(angle), np.sin(angle)
    out = np.eye(4)
    out[:3, :3] = [[c, 0, s_], [0, 1, 0], [-s_, 0, c]]
    return out


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
        roll: roll every frame horizontally by this many columns first (a yaw of the camera).
    """
    seq_length = int(predictor.config.data.seq_length)
    k = (seq_length - 1) // 2
    m = len(images)
    centres = list(range(k, m - k))
    chunks = [centres[i : i + batch_size] for i in range(0, len(centres), batch_size)]
    windows: dict[int, np.ndarray] = {}

    def load(chunk: list[int]) -> torch.Tensor:
        frames = [load_image(images[f]) for f in range(chunk[0] - k, chunk[-1] + k + 1)]
        batch = _to_tensor(frames)
        return torch.roll(batch, roll, dims=-1) if roll else batch

    bar = _progress(len(centres), desc, progress)
    with ThreadPoolExecutor(max_workers=2) as pool:
        for chunk, frames in zip(chunks, _prefetch(pool, load, chunks, 2), strict=True):
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


# --------------------------------------------------------------------------------------- evo metrics
def _evo_traj(c2w: np.ndarray, times: np.ndarray) -> Any:
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(
        poses_se3=[np.asarray(p, dtype=np.float64) for p in c2w], timestamps=np.asarray(times)
    )


def _evo_stats(ref: Any, est: Any, rpe: bool) -> dict[str, float | None]:
    from evo.core import metrics
    from evo.core.units import Unit

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    st = ape.get_all_statistics()
    out: dict[str, float | None] = {
        "ape_rmse": float(st["rmse"]),
        "ape_mean": float(st["mean"]),
        "ape_median": float(st["median"]),
        "ape_max": float(st["max"]),
        "rpe_trans_rmse": None,
        "rpe_rot_deg_rmse": None,
    }
    if rpe and ref.num_poses >= 2:
        for key, rel in (
            ("rpe_trans_rmse", metrics.PoseRelation.translation_part),
            ("rpe_rot_deg_rmse", metrics.PoseRelation.rotation_angle_deg),
        ):
            r = metrics.RPE(rel, delta=1, delta_unit=Unit.frames, all_pairs=False)
            r.process_data((ref, est))
            out[key] = float(r.get_statistic(metrics.StatisticsType.rmse))
    return out


def trajectory_metrics(
    gt_c2w: np.ndarray,
    gt_times: np.ndarray,
    est_c2w: np.ndarray,
    est_times: np.ndarray,
    max_diff: float = 0.01,
) -> tuple[dict[str, Any], np.ndarray | None]:
    """APE and RPE of an estimated trajectory against ground truth, with ``evo``.

    The trajectories are associated by timestamp (``evo.core.sync``, within ``max_diff`` seconds), a copy
    of the estimate is Sim(3)-aligned to the ground truth (``align(correct_scale=True)``), then APE
    (translation part) and RPE (delta 1 frame; translation and rotation angle) are computed on it.

    Args:
        gt_c2w, est_c2w: camera-to-world poses ``[N,4,4]`` / ``[K,4,4]`` (ground truth in metres).
        gt_times, est_times: their timestamps ``[N]`` / ``[K]``.

    Returns:
        ``({ape_rmse, ape_mean, ape_median, ape_max, rpe_trans_rmse, rpe_rot_deg_rmse (metres, degrees),
        scale (of the alignment), n_frames}, aligned positions [n,3])``. When the alignment is degenerate
        (collinear or coincident estimated positions) the measures are ``None``, ``"error"`` says why and
        the positions are ``None``.
    """
    from evo.core import sync
    from evo.core.geometry import GeometryException

    ref = _evo_traj(gt_c2w, gt_times)
    est = _evo_traj(est_c2w, est_times)
    try:
        ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
    except sync.SyncException as exc:
        raise DatasetError(f"no estimated pose matches the ground-truth timestamps ({exc})") from None
    aligned = copy.deepcopy(est)
    base: dict[str, Any] = {"n_frames": int(ref.num_poses)}
    try:
        _, _, scale = aligned.align(ref, correct_scale=True)
    except GeometryException as exc:
        return {**dict.fromkeys(TRAJECTORY_METRICS), "scale": None, **base, "error": str(exc)}, None
    stats = _evo_stats(ref, aligned, rpe=True)
    return {**stats, "scale": float(scale), **base}, np.asarray(aligned.positions_xyz)


def _rotation_z_to(v: np.ndarray) -> np.ndarray:
    """A rotation taking +z to the direction of ``v`` (identity for a zero vector)."""
    n = float(np.linalg.norm(v))
    if n == 0:
        return np.eye(3)
    d = v / n
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    s, c = float(np.linalg.norm(axis)), float(d @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    a = axis / s
    kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    ang = math.atan2(s, c)
    return np.eye(3) + math.sin(ang) * kx + (1 - math.cos(ang)) * (kx @ kx)


def _baseline_trajectories(
    gt_c2w: np.ndarray, times: np.ndarray, index: np.ndarray
) -> tuple[dict[str, dict[str, Any]], dict[str, np.ndarray]]:
    """Full-trajectory metrics of the baselines on the given frames (``index``: their chain indices)."""
    pos = gt_c2w[:, :3, 3]
    # constant velocity, optimally Sim(3)-aligned: least-squares line c + v i through the positions
    design = np.stack((np.ones(len(index)), index.astype(np.float64)), 1)
    coef, *_ = np.linalg.lstsq(design, pos, rcond=None)
    line = design @ coef
    cv = np.tile(np.eye(4), (len(index), 1, 1))
    cv[:, :3, :3] = _rotation_z_to(coef[1])
    cv[:, :3, 3] = line
    ref = _evo_traj(gt_c2w, times)
    cv_stats = _evo_stats(ref, _evo_traj(cv, times), rpe=True)
    cv_stats["scale"] = float(np.linalg.norm(coef[1]))
    cv_stats["n_frames"] = len(index)
    # zero motion: a camera standing at the centroid
    zero = np.tile(gt_c2w[0], (len(index), 1, 1))
    zero[:, :3, 3] = pos.mean(0)
    z_stats = _evo_stats(ref, _evo_traj(zero, times), rpe=False)
    z_stats["n_frames"] = len(index)
    return {"constant_velocity": cv_stats, "zero_motion": z_stats}, {"constant velocity": line}


# --------------------------------------------------------------------------------------- plots
def plot_trajectories(
    path: PathLike, gt_xyz: np.ndarray, curves: dict[str, np.ndarray | None], title: str = ""
) -> None:
    """Save a top view (x right, z up the page; the world's y points down) of aligned trajectories
    ``{name: [N,3]}`` against the ground truth ``[N,3]`` as a PNG (matplotlib's Agg canvas, written
    atomically; the global matplotlib backend is left alone)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    gt = np.asarray(gt_xyz)
    ax.plot(gt[:, 0], gt[:, 2], "k-", lw=2, label="ground truth")
    ax.plot(gt[:1, 0], gt[:1, 2], "ko", ms=5)
    styles = ["-", "--", ":", "-."]
    for n, (name, xyz) in enumerate(curves.items()):
        if xyz is None:
            continue
        xyz = np.asarray(xyz)
        ax.plot(xyz[:, 0], xyz[:, 2], styles[n % len(styles)], lw=1.5, label=name)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(path, buf.getvalue())


# --------------------------------------------------------------------------------------- evaluation
def _match(gt_times: np.ndarray, est_times: np.ndarray, tol: float) -> np.ndarray:
    """For each ground-truth time the index of the nearest estimated time within ``tol``, else -1."""
    out = np.full(len(gt_times), -1, dtype=np.int64)
    if len(est_times) == 0:
        return out
    order = np.argsort(est_times, kind="stable")
    srt = est_times[order]
    pos = np.searchsorted(srt, gt_times)
    for i, (t, p) in enumerate(zip(gt_times, pos, strict=True)):
        best, bd = -1, math.inf
        for q in (p - 1, p):
            if 0 <= q < len(srt) and abs(srt[q] - t) < bd:
                best, bd = int(order[q]), abs(srt[q] - t)
        if bd <= tol:
            out[i] = best
    return out


def _trajectory_file(path: Path, seq: SequenceInfo, n_sequences: int) -> Path:
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


def _summary(values: list[np.ndarray]) -> dict[str, Any]:
    allv = np.concatenate(values) if values else np.zeros(0)
    n = int(allv.size)
    return {
        "ate_mean": float(allv.mean()) if n else math.nan,
        "ate_std": float(allv.std()) if n else math.nan,
        "n_snippets": n,
    }


def _average(per_seq: list[dict[str, Any]], keys: Sequence[str]) -> dict[str, Any]:
    out = {}
    for k in keys:
        vals = [d[k] for d in per_seq if d.get(k) is not None]
        out[k] = float(np.mean(vals)) if vals else None
    return out


def evaluate_pose(
    predictor_or_trajectory: Any,
    data_root: PathLike,
    split: str | PathLike | None = "test",
    split_name: str = "default",
    snippet: int = 5,
    stride: int | None = None,
    out: PathLike | None = None,
    batch_size: int = 8,
    progress: bool | None = False,
    yaw_roll: int | None = None,
) -> dict[str, Any]:
    """Evaluate ego-motion on a dataset's ground-truth poses, with the zero-motion and constant-velocity
    baselines (protocol in the module docstring).

    Args:
        predictor_or_trajectory: a :class:`cylsfm.model.Predictor`, or the TUM trajectory of another
            method: a directory with ``SEQ.txt`` per evaluated sequence, or one file when a single
            sequence is evaluated.
        data_root: the dataset root; evaluated sequences need ``poses.txt`` for the metrics (others are
            skipped with a warning, their trajectories still written).
        split: sequences with a target in this split (``"test"``, ``"val"``, ``"train"`` or a split file)
            are evaluated whole; ``None``: every sequence.
        split_name: the split directory under ``ROOT/splits``.
        snippet: frames per ATE snippet.
        stride: frame step of the chain (default: the model's ``data.stride``; 1 for trajectories).
        out: directory for ``SEQ.txt`` (the model's chained trajectory, TUM, camera-to-world, network
            units, timestamps of ``poses.txt`` or the frame index) and ``SEQ.png`` (top view of the
            aligned trajectories); ``None``: write nothing.
        batch_size: windows per network call.
        progress: show progress bars (``None``: when stderr is a terminal).
        yaw_roll: a seed: roll every frame of each evaluated sequence by a random number of columns
            (drawn per sequence) before the network sees it, as if the 360-degree camera had been mounted
            turned about its vertical axis. The ground truth is turned with it
            (``c2w' = c2w @ inv(yaw_matrix(2 pi k / W))``). Full panoramas and models only. This is how
            the paper's pose head (invariant to such rolls) and the yaw-equivariant head are compared.

    Returns:
        ``{"model": {ate_mean, ate_std, n_snippets, ape_rmse, ...}, "zero_motion": {...},
        "constant_velocity": {...}, "sequences": {SEQ: {...}}, "n_snippets", "snippet", "stride",
        "source", "data", "split", "split_name", "out"}``; see :func:`pose_json`.
    """
    if snippet < 2:
        raise ValueError(f"snippet must be at least 2 frames, got {snippet}")
    root = Path(data_root)
    sequences = scan_dataset(root)
    entries = split_entries(root, split, split_name, sequences)
    names = None if entries is None else {s for s, _ in entries}
    chosen = [s for s in sequences if names is None or s.name in names]
    if not chosen:
        raise DatasetError(f"{root}: split {split} names no sequence")

    predictor = None
    traj_path: Path | None = None
    if isinstance(predictor_or_trajectory, (str, os.PathLike)):
        traj_path = Path(predictor_or_trajectory)
        step = int(stride or 1)
        source = f"trajectory {traj_path}"
        files = {s.name: _trajectory_file(traj_path, s, len(chosen)) for s in chosen}
    else:
        predictor = predictor_or_trajectory
        step = int(stride or predictor.config.data.stride)
        source = f"checkpoint {getattr(getattr(predictor, 'models', None), 'path', '?')}"
    if step < 1:
        raise ValueError(f"stride must be >= 1, got {step}")
    out_dir = None if out is None else Path(out)

    if yaw_roll is not None and predictor is None:
        raise ValueError("yaw_roll applies to a model's predictions, not to a given trajectory")
    snippets: dict[str, list[np.ndarray]] = {"model": [], "zero_motion": [], "constant_velocity": []}
    per_seq: dict[str, dict[str, Any]] = {}
    for n_seq, seq in enumerate(chosen):
        index = np.arange(0, len(seq), step)
        m = len(index)
        times = seq.timestamps[index] if seq.timestamps is not None else index.astype(np.float64)
        info: dict[str, Any] = {"n_frames": m}
        gt = None if seq.poses is None else seq.poses[index]
        roll = 0
        if yaw_roll is not None:
            if not seq.camera.wraps:
                raise DatasetError(f"{seq.path / 'camera.json'}: yaw rolls need full 360-degree panoramas")
            roll = int(np.random.default_rng([yaw_roll, n_seq]).integers(seq.camera.width))
            info["yaw_roll_columns"] = roll
            if gt is not None:
                gt = gt @ np.linalg.inv(_yaw4(2 * np.pi * roll / seq.camera.width))
        # ---- the estimate on the chain frames
        if predictor is not None:
            seq_length = int(predictor.config.data.seq_length)
            if m < seq_length:
                warnings.warn(
                    f"{seq.path}: {m} frames (stride {step}) are fewer than one window of {seq_length}; skipped",
                    DatasetWarning,
                    stacklevel=2,
                )
                continue
            steps = predict_consecutive(
                predictor, [seq.images[i] for i in index], seq.camera, batch_size, progress, seq.name, roll
            )
            est = chain_poses(steps)
            matched = np.ones(m, dtype=bool)
            if out_dir is not None:
                write_tum(out_dir / f"{seq.name}.txt", times, est)
                info["tum"] = str(out_dir / f"{seq.name}.txt")
        else:
            t_est, c2w_est = read_tum(files[seq.name])
            gaps = np.diff(times)
            tol = 0.5 * float(gaps[gaps > 0].min()) if (gaps > 0).any() else 1e-3
            which = _match(times, t_est, tol)
            matched = which >= 0
            est = np.tile(np.eye(4), (m, 1, 1))
            est[matched] = c2w_est[which[matched]]
        info["n_matched"] = int(matched.sum())
        if gt is None:
            warnings.warn(
                f"{seq.path / 'poses.txt'}: not found; sequence {seq.name} not scored",
                DatasetWarning,
                stacklevel=2,
            )
            per_seq[seq.name] = info
            continue
        # ---- snippets
        ates = snippet_ates(gt, est, snippet, matched)
        for k, v in ates.items():
            snippets[k].append(v)
        info["n_snippets"] = len(ates["model"])
        info["ate_mean"] = float(ates["model"].mean()) if len(ates["model"]) else None
        # ---- full trajectories
        sel = np.nonzero(matched)[0]
        if len(sel) >= 3:
            model_m, aligned = trajectory_metrics(gt[sel], times[sel], est[sel], times[sel], max_diff=1e-6)
            base_m, base_curves = _baseline_trajectories(gt[sel], times[sel], sel)
            info["model"] = model_m
            info.update(base_m)
            if out_dir is not None:
                png = out_dir / f"{seq.name}.png"
                plot_trajectories(
                    png,
                    gt[sel, :3, 3],
                    {"model (Sim(3)-aligned)": aligned, **base_curves},
                    title=f"{seq.name}: top view",
                )
                info["plot"] = str(png)
        per_seq[seq.name] = info

    if not any(len(v) for v in snippets["zero_motion"]) and not any("model" in d for d in per_seq.values()):
        raise DatasetError(
            f"{root}: nothing to score (evaluated sequences need poses.txt and at least {snippet} frames)"
        )
    scored = [d for d in per_seq.values() if "model" in d]
    model = {**_summary(snippets["model"]), **_average([d["model"] for d in scored], TRAJECTORY_METRICS)}
    zero = {
        **_summary(snippets["zero_motion"]),
        **_average([d["zero_motion"] for d in scored], ("ape_rmse", "ape_mean", "ape_median", "ape_max")),
    }
    cv = {
        **_summary(snippets["constant_velocity"]),
        **_average([d["constant_velocity"] for d in scored], TRAJECTORY_METRICS),
    }
    return {
        "model": model,
        "zero_motion": zero,
        "constant_velocity": cv,
        "sequences": per_seq,
        "n_snippets": model["n_snippets"],
        "snippet": int(snippet),
        "stride": step,
        "source": source,
        "data": str(root),
        "split": None if split is None else str(split),
        "split_name": split_name,
        "out": None if out_dir is None else str(out_dir),
        "yaw_roll": yaw_roll,
    }


# --------------------------------------------------------------------------------------- reporting
def pose_json(result: dict[str, Any]) -> dict[str, Any]:
    """The JSON layout of a result of :func:`evaluate_pose`::

    {"ate_mean", "ate_std", "n_snippets",                         snippet ATE of the model (metres)
     "ape_rmse", "ape_mean", "ape_median", "ape_max",              Sim(3)-aligned APE, mean over sequences
     "rpe_trans_rmse", "rpe_rot_deg_rmse",                         RPE, delta 1 frame
     "baselines": {"zero_motion": {"ate_mean", "ate_std", "n_snippets", "ape_rmse", "ape_mean",
                                   "ape_median", "ape_max"},
                   "constant_velocity": {same keys as the model}},
     "sequences": {SEQ: {"n_frames", "n_matched", "n_snippets", "ate_mean", "model": {...},
                         "zero_motion": {...}, "constant_velocity": {...}, "tum", "plot"}},
     "meta": {"source", "data", "split", "split_name", "snippet", "stride", "out", "yaw_roll"}}
    """
    out = dict(result["model"])
    out["baselines"] = {
        "zero_motion": result["zero_motion"],
        "constant_velocity": result["constant_velocity"],
    }
    out["sequences"] = result["sequences"]
    out["meta"] = {
        k: result.get(k)
        for k in ("source", "data", "split", "split_name", "snippet", "stride", "out", "yaw_roll")
    }
    return out


def _fmt(v: Any, width: int = 11) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-".rjust(width)
    return f"{v:{width}.4f}"


def format_pose_table(result: dict[str, Any]) -> str:
    """A readable table of a result of :func:`evaluate_pose`: model and baselines, then the ratios
    model / baseline (below 1 is better)."""
    cols = ("ate_mean", "ate_std", "ape_rmse", "rpe_trans_rmse", "rpe_rot_deg_rmse")
    lines = [
        f"pose: {result['n_snippets']} snippets of {result['snippet']} frames (stride {result['stride']}), "
        f"{len(result['sequences'])} sequences ({result['source']}); metres and degrees, lower is better",
        f"{'':26}" + "".join(f"{c:>17}" for c in cols),
    ]
    rows: list[tuple[str, dict[str, Any]]] = [
        ("model", result["model"]),
        ("zero motion", result["zero_motion"]),
        ("constant velocity", result["constant_velocity"]),
    ]
    for name, m in rows:
        lines.append(f"{name:26}" + "".join(_fmt(m.get(c), 17) for c in cols))
    for name, m in rows[1:]:
        ratios = []
        for c in cols:
            a, b = result["model"].get(c), m.get(c)
            ok = a is not None and b is not None and math.isfinite(a) and math.isfinite(b) and b != 0
            ratios.append(a / b if ok else None)
        lines.append(f"{'model/' + name:26}" + "".join(_fmt(r, 17) for r in ratios))
    return "\n".join(lines)
