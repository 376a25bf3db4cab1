"""Pose measures as small functions: SfMLearner's snippet ATE, chaining the network's relative poses into a
trajectory, and full-trajectory APE / RPE with ``evo``, with the closed-form alignments of the baselines.

Poses are 4x4 NumPy arrays (float64): camera-to-world ``c2w [N,4,4]`` (ground truth in metres, estimates in
any units) or relative ``T_{j->j+1}`` (``p_{j+1} = T p_j``). The protocol that uses them is described in
:mod:`cylsfm.evaluate.pose`.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..data import DatasetError
from ..errors import InputError
from ..geometry import invert, rotation_x, rotation_y

__all__ = [
    "TRAJECTORY_METRICS",
    "ate_positions",
    "ate_summary",
    "average_metrics",
    "baseline_trajectories",
    "chain_poses",
    "consecutive_from_windows",
    "constant_velocity_trajectory",
    "evo_statistics",
    "evo_trajectory",
    "match_times",
    "relative_positions",
    "snippet_ate",
    "snippet_ates",
    "step_from_window",
    "trajectory_metrics",
    "window_centre",
]

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
        raise InputError(f"gt and pred must both be [N,3] with N >= 1, got {g.shape} and {p.shape}")
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
        raise InputError(f"snippet must be at least 2 frames, got {snippet}")
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
def chain_poses(steps: np.ndarray) -> np.ndarray:
    """Camera-to-world poses ``[M,4,4]`` (first = identity) from consecutive relative poses
    ``steps [M-1,4,4]`` = ``T_{j->j+1}`` (target ``j``, source ``j+1``: ``p_{j+1} = T p_j``):
    ``c2w_{j+1} = c2w_j @ inv(T_{j->j+1})``. Each step's rotation is first brought to the nearest rotation
    (a float32 step is one to about 1e-7; chained over a thousand frames, that would no longer be a
    rotation by evo's test)."""
    steps = np.array(steps, dtype=np.float64)
    if len(steps):
        u, _, vt = np.linalg.svd(steps[:, :3, :3])
        flip = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)
        u[:, :, 2] *= flip[:, None]
        steps[:, :3, :3] = u @ vt
    out = np.tile(np.eye(4), (len(steps) + 1, 1, 1))
    for j, t in enumerate(steps):
        out[j + 1] = out[j] @ invert(t)
    return out


def window_centre(j: int, m: int, k: int) -> int:
    """The centre of the window that gives step ``j`` of a chain of ``m`` frames (windows of ``2k+1``): ``j``
    itself, or the nearest full window near the ends."""
    return min(max(j, k), m - 1 - k)


def step_from_window(window: np.ndarray, c: int, j: int, k: int) -> np.ndarray:
    """``T_{j->j+1}`` ``[4,4]`` from the window centred on ``c`` (``window``: ``T_{c->src}`` ``[2k,4,4]``,
    sources ``c-k .. c+k`` without ``c`` in time order; ``c-k <= j < j+1 <= c+k``)."""
    eye = np.eye(4)

    def t_from(f: int) -> np.ndarray:  # T_{c->f}
        if f == c:
            return eye
        o = f - c
        return np.asarray(window[o + k if o < 0 else o + k - 1], dtype=np.float64)

    return t_from(j + 1) @ invert(t_from(j))


def consecutive_from_windows(windows: dict[int, np.ndarray], m: int, seq_length: int) -> np.ndarray:
    """Consecutive relative poses ``T_{j->j+1}`` ``[M-1,4,4]`` from the network's windows.

    Args:
        windows: ``c -> [L-1,4,4]``: ``T_{c->src}`` for the window centred on chain frame ``c``, sources in
            time order (frames ``c-k .. c+k`` without ``c``), for every ``c`` in ``k .. M-1-k``.
        m: number of chain frames ``M`` (at least ``L``).
        seq_length: ``L``, odd.

    Returns:
        ``T_{j->j+1}`` from the window centred on ``j``, or on the nearest full window near the ends
        (:func:`window_centre`).
    """
    k = (seq_length - 1) // 2
    if m < seq_length:
        raise InputError(f"{m} frames are fewer than one window of {seq_length}")
    out = np.empty((m - 1, 4, 4))
    for j in range(m - 1):
        c = window_centre(j, m, k)
        out[j] = step_from_window(windows[c], c, j, k)
    return out


# --------------------------------------------------------------------------------------- evo metrics
def evo_trajectory(c2w: np.ndarray, times: np.ndarray) -> Any:
    """An ``evo`` ``PoseTrajectory3D`` of camera-to-world poses ``[N,4,4]`` at timestamps ``[N]``."""
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(
        poses_se3=[np.asarray(p, dtype=np.float64) for p in c2w], timestamps=np.asarray(times)
    )


def evo_statistics(ref: Any, est: Any, rpe: bool) -> dict[str, float | None]:
    """APE (translation part: rmse, mean, median, max) of ``est`` against ``ref`` (associated ``evo``
    trajectories, already aligned) and, with ``rpe``, the RPE rmse between consecutive frames (translation,
    rotation angle in degrees; ``None`` without ``rpe`` or with fewer than 2 poses)."""
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

    ref = evo_trajectory(gt_c2w, gt_times)
    est = evo_trajectory(est_c2w, est_times)
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
    stats = evo_statistics(ref, aligned, rpe=True)
    return {**stats, "scale": float(scale), **base}, np.asarray(aligned.positions_xyz)


def _heading_rotation(v: np.ndarray) -> np.ndarray:
    """A rotation ``[3,3]`` taking +z (forward) to the direction of ``v [3]`` (identity for a zero vector):
    a yaw to ``v``'s azimuth after a pitch to its elevation (y points down)."""
    azimuth = math.atan2(float(v[0]), float(v[2]))
    elevation = math.atan2(-float(v[1]), math.hypot(float(v[0]), float(v[2])))
    return rotation_y(np.asarray(azimuth)) @ rotation_x(np.asarray(elevation))


def baseline_trajectories(
    gt_c2w: np.ndarray, times: np.ndarray, index: np.ndarray
) -> tuple[dict[str, dict[str, Any]], dict[str, np.ndarray]]:
    """Full-trajectory metrics of the baselines on the given frames (``index``: their chain indices)."""
    pos = gt_c2w[:, :3, 3]
    # constant velocity, optimally Sim(3)-aligned: least-squares line c + v i through the positions
    design = np.stack((np.ones(len(index)), index.astype(np.float64)), 1)
    coef, *_ = np.linalg.lstsq(design, pos, rcond=None)
    line = design @ coef
    cv = np.tile(np.eye(4), (len(index), 1, 1))
    cv[:, :3, :3] = _heading_rotation(coef[1])
    cv[:, :3, 3] = line
    ref = evo_trajectory(gt_c2w, times)
    cv_stats = evo_statistics(ref, evo_trajectory(cv, times), rpe=True)
    cv_stats["scale"] = float(np.linalg.norm(coef[1]))
    cv_stats["n_frames"] = len(index)
    # zero motion: a camera standing at the centroid
    zero = np.tile(gt_c2w[0], (len(index), 1, 1))
    zero[:, :3, 3] = pos.mean(0)
    z_stats = evo_statistics(ref, evo_trajectory(zero, times), rpe=False)
    z_stats["n_frames"] = len(index)
    return {"constant_velocity": cv_stats, "zero_motion": z_stats}, {"constant velocity": line}


# --------------------------------------------------------------------------------------- association, averages
def match_times(gt_times: np.ndarray, est_times: np.ndarray, tol: float) -> np.ndarray:
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


def ate_summary(values: list[np.ndarray]) -> dict[str, Any]:
    """``{"ate_mean", "ate_std" (population), "n_snippets"}`` over all snippet ATEs of all sequences
    (``values``: one ``[n]`` array per sequence); NaN when there is no snippet."""
    allv = np.concatenate(values) if values else np.zeros(0)
    n = int(allv.size)
    return {
        "ate_mean": float(allv.mean()) if n else math.nan,
        "ate_std": float(allv.std()) if n else math.nan,
        "n_snippets": n,
    }


def average_metrics(per_seq: list[dict[str, Any]], keys: Sequence[str]) -> dict[str, Any]:
    """The mean of each of ``keys`` over the per-sequence dicts that have it (each sequence weighs the
    same; ``None`` values are left out), or ``None`` when none has it."""
    out = {}
    for k in keys:
        vals = [d[k] for d in per_seq if d.get(k) is not None]
        out[k] = float(np.mean(vals)) if vals else None
    return out
