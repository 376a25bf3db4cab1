"""How good a ride's trajectory is, when the input has ground truth: evo's APE (Sim(3)-aligned) and RPE of
the trajectory and of the references beside it, and the error of every step.

References, none of which learned anything about this ride: the pose network alone (when the trajectory
is refined), the visual compass (the yaw between the panoramas, with the network's translation), constant velocity
(the best straight line at constant speed) and zero motion.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..evaluate.motion import rotation_error_deg, turn_response
from ..evaluate.plots import plot_trajectories
from ..evaluate.pose_metrics import baseline_trajectories, chain_poses, trajectory_metrics
from ..geometry import invert

__all__ = ["direction_error_deg", "ride_metrics", "top_view"]


def direction_error_deg(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the translations of relative poses ``[N,4,4]``; ``nan`` where either is
    zero (a standing camera has no direction)."""
    a, b = pred[:, :3, 3], true[:, :3, 3]
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    ok = (na > 1e-12) & (nb > 1e-9)
    cos = np.einsum("ij,ij->i", a, b) / np.where(ok, na * nb, 1.0)
    return np.where(ok, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), np.nan)


def _step_errors(steps: np.ndarray, gt_steps: np.ndarray) -> dict[str, float]:
    rot = rotation_error_deg(steps, gt_steps)
    direction = direction_error_deg(steps, gt_steps)
    turns = turn_response(steps, gt_steps)
    return {
        "n_turning": turns["n_turning"],
        "yaw_slope": turns["yaw_slope"],
        "rot_err_deg_turning": turns["rot_err_deg_turning"],
        "rot_err_deg_mean": float(np.mean(rot)),
        "rot_err_deg_median": float(np.median(rot)),
        "dir_err_deg_mean": float(np.nanmean(direction)) if np.isfinite(direction).any() else None,
        "dir_err_deg_median": float(np.nanmedian(direction)) if np.isfinite(direction).any() else None,
    }


def ride_metrics(
    gt_times: np.ndarray, gt_c2w: np.ndarray, steps: dict[str, np.ndarray | None]
) -> tuple[dict[str, Any], dict[str, np.ndarray | None]]:
    """Measures of each trajectory given by its steps ``T_{j->j+1}`` ``[M-1,4,4]`` against the ground truth.

    Returns:
        ``({name: {ape_rmse, ..., rot_err_deg_mean, dir_err_deg_mean, ...}}, {name: aligned positions}``):
        every entry of ``steps`` and ``constant_velocity`` and ``zero_motion``.
    """
    gt_steps = np.stack([invert(gt_c2w[j + 1]) @ gt_c2w[j] for j in range(len(gt_c2w) - 1)])
    out: dict[str, Any] = {}
    curves: dict[str, np.ndarray | None] = {}
    for name, st in steps.items():
        if st is None:
            continue
        stats, aligned = trajectory_metrics(gt_c2w, gt_times, chain_poses(st), gt_times)
        out[name] = {**stats, **_step_errors(st, gt_steps)}
        curves[name] = aligned
    base, lines = baseline_trajectories(gt_c2w, gt_times, np.arange(len(gt_c2w)))
    out.update(base)
    curves["constant velocity"] = lines["constant velocity"]
    return out, curves


def top_view(
    path: Path,
    c2w: np.ndarray,
    unit: str,
    gt: np.ndarray | None,
    curves: dict[str, Any],
    links: list[tuple[int, int]] | None = None,
) -> None:
    """The ride seen from above: the aligned curves against the ground truth, or the trajectory alone;
    ``links``: frame pairs (the accepted loops) drawn between the first curve's positions."""
    if gt is None:
        xyz = c2w[:, :3, 3]
        plot_trajectories(
            path,
            None,
            {"trajectory": xyz},
            title="trajectory (top view)",
            unit=unit,
            links=_links(xyz, links),
        )
        return
    first = next((c for c in curves.values() if c is not None), None)
    plot_trajectories(
        path,
        gt[:, :3, 3],
        curves,
        title="Sim(3)-aligned to the ground truth (top view)",
        links=_links(first, links),
    )


def _links(xyz: np.ndarray | None, pairs: list[tuple[int, int]] | None) -> np.ndarray | None:
    """``[K,2,3]`` the positions of the frame pairs on a curve ``[N,3]`` (``None``: none)."""
    if xyz is None or not pairs:
        return None
    xyz = np.asarray(xyz)
    return np.stack([xyz[[i, j]] for i, j in pairs])
