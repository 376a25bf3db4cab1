"""The last stage of :func:`cylsfm.odometry`: the trajectory, the network's own, the top view, the measures
against the ground truth and the summary, written into the output directory; and the
:class:`OdometryResult` that the caller (and the exports) get."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._version import __version__
from ..atomic import atomic_write_text
from ..data.io import write_tum
from ..evaluate.pose_metrics import chain_poses
from .depth import DepthScale
from .loops import Loop
from .mount import mount_summary
from .report import ride_metrics, top_view
from .scale import Scaled
from .state import State

if TYPE_CHECKING:
    from .job import Job

__all__ = ["SUMMARY_FILE", "OdometryResult", "Steps", "loop_summary", "write_outputs"]

#: The summary's file name in the output directory.
SUMMARY_FILE = "odometry.json"


@dataclass
class OdometryResult:
    """What :func:`cylsfm.odometry` wrote and measured.

    Attributes:
        trajectory: the TUM file (``OUT/trajectory.txt``).
        c2w: the camera-to-world poses ``[M,4,4]`` written there; ``times`` ``[M]``, ``frames`` their names.
        unit: ``"network units"`` or ``"metres"``; ``metres_per_unit`` the scale applied (``None``: none).
        metrics: measures against the ground truth (``None`` without it), as in ``OUT/metrics.json``.
        timings: seconds per part of the work; ``seconds`` in all.
        loops: what the loop closure found (as ``odometry.json``'s ``loops``; ``None``: not looked for).
        bundle: the bundle adjustment's counts and seconds (as ``odometry.json``'s ``bundle``; ``None``:
            not adjusted).
        out: the output directory; ``depth``: its folder of depth maps in the trajectory's unit (``None``:
            none written).
        fingerprint: the fingerprint of the run's identity (:attr:`cylsfm.odometry.job.Job.identity`).
    """

    trajectory: Path
    c2w: np.ndarray
    times: np.ndarray
    frames: list[str]
    unit: str
    metres_per_unit: float | None
    metrics: dict[str, Any] | None
    timings: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    loops: dict[str, Any] | None = None
    bundle: dict[str, float] | None = None
    out: Path | None = None
    depth: Path | None = None
    fingerprint: str = ""


@dataclass
class Steps:
    """The ride's consecutive steps ``T_{j->j+1}`` ``[M-1,4,4]`` at each stage (``None``: not made)."""

    network: np.ndarray
    compass: np.ndarray
    refined: np.ndarray | None
    steady: np.ndarray | None
    closed: np.ndarray | None
    adjusted: np.ndarray | None = None


def write_outputs(
    job: Job,
    state: State,
    steps: Steps,
    scaled: Scaled,
    loops: list[Loop] | None,
    bundle: dict[str, float] | None,
    timings: dict[str, float],
    seconds: float,
    depth_scale: DepthScale | None = None,
) -> OdometryResult:
    """Write ``trajectory.txt`` (and with ``refine`` ``trajectory_network.txt``), ``trajectory.png``,
    ``metrics.json`` (with ground truth) and ``odometry.json``; ``bundle``: the bundle adjustment's counts
    (``None``: not adjusted); ``seconds``: the run's time so far; ``depth_scale``: the depth files'
    factors to the adjusted points (``None``: one factor for all)."""
    dest, opt = job.out, job.settings
    c2w, times = chain_poses(scaled.steps), np.asarray(state.times)
    summary_of_loops = loop_summary(loops)
    masked, mount = _mask_summary(job), mount_summary(job.mount_yaw, state.mount)
    header = _header(job, scaled, masked, mount, summary_of_loops)
    if bundle is not None:
        header.append(
            f"bundle adjusted: {bundle['points']:.0f} points, {bundle['kept']:.0f} of "
            f"{bundle['observations']:.0f} observations kept"
        )
    write_tum(dest / "trajectory.txt", times, c2w, header)
    if opt.refine:
        network = chain_poses(steps.network)
        write_tum(dest / "trajectory_network.txt", times, network, ["the pose network alone"])
    measured = _measure(job, state, steps)
    truth, curves = (measured[1], measured[2]) if measured else (None, {})
    unit = "m" if scaled.metres_per_unit or job.depth.truth else "network units"
    links = [(lp.i, lp.j) for lp in loops or [] if lp.accepted]
    top_view(dest / "trajectory.png", c2w, unit, truth, curves, links=links)
    summary = {
        "input": str(job.ride.path),
        "frames": len(c2w),
        "unit": scaled.unit,
        "metres_per_unit": scaled.metres_per_unit,
        "refined": opt.refine,
        "steady_height": opt.steady_height,
        "seconds": seconds,
        "frames_per_second": len(c2w) / seconds if seconds > 0 else None,
        "timings": timings,
        "refinement": _refine_stats(state) if opt.refine else None,
        "direction_of_travel": mount,
        "mask": masked,
        "loops": summary_of_loops,
        "bundle": bundle,
        "depth_maps": opt.save_depth_maps,
        "depth_scale": depth_scale.to_dict() if depth_scale is not None else None,
        "fingerprint": job.fingerprint,
        "settings": job.identity,
    }
    atomic_write_text(dest / SUMMARY_FILE, json.dumps(summary, indent=2) + "\n")
    if measured:
        atomic_write_text(dest / "metrics.json", json.dumps(measured[0], indent=2) + "\n")
    return OdometryResult(
        trajectory=dest / "trajectory.txt",
        c2w=c2w,
        times=times,
        frames=list(state.stems),
        unit=scaled.unit,
        metres_per_unit=scaled.metres_per_unit,
        metrics=measured[0] if measured else None,
        timings=timings,
        seconds=seconds,
        loops=summary_of_loops,
        bundle=bundle,
        out=dest,
        depth=dest / "depth" if opt.save_depth_maps else None,
        fingerprint=job.fingerprint,
    )


def _header(
    job: Job,
    scaled: Scaled,
    masked: dict[str, Any] | None,
    mount: dict[str, Any] | None,
    loops: dict[str, Any] | None,
) -> list[str]:
    """The trajectory file's comment lines: the unit, how the steps were made, the mask, the direction of
    travel, the loops."""
    opt = job.settings
    how = (", refined by direct alignment" if opt.refine else "") + (
        ", steady camera height" if opt.steady_height else ""
    )
    lines = [scaled.note, f"cylsfm {__version__} odometry of {job.ride.path}{how}"]
    if masked is not None:
        lines.append(f"mask: {masked['file']} ({masked['occluded_fraction']:.1%} of the pixels left out)")
    if mount is not None:
        lines.append(f"direction of travel in the panorama: {mount['yaw_deg']:.1f} deg ({mount['how']})")
    if loops is not None:
        line = f"loops: {loops['verified']} candidate pairs verified, {loops['accepted']} accepted"
        lines.append(line + (" (closed by a pose graph)" if loops["accepted"] else ""))
    return lines


def _mask_summary(job: Job) -> dict[str, Any] | None:
    if job.mask is None:
        return None
    return {"file": str(job.mask_file), "occluded_fraction": float(1 - job.mask.mean())}


def loop_summary(loops: list[Loop] | None) -> dict[str, Any] | None:
    """What the loop closure found (``None``: not looked for): per verified pair its frames, whether it was
    accepted (the reason's code and words when not), the inlier fraction, the yaw, the scale ratio and
    the relative pose ``T_{i->j}`` (16 numbers, row by row; translation in frame ``i``'s depth unit)."""
    if loops is None:
        return None
    return {
        "verified": len(loops),
        "accepted": sum(lp.accepted for lp in loops),
        "pairs": [
            {
                "i": lp.i,
                "j": lp.j,
                "accepted": lp.accepted,
                "reason": lp.reason.value,
                "why": lp.reason.message,
                "inliers": lp.inliers,
                "yaw_deg": lp.yaw_deg,
                "scale_ratio": lp.ratio,
                "pose": [round(float(v), 6) for v in lp.pose.ravel()],
            }
            for lp in loops
        ],
    }


def _refine_stats(state: State) -> dict[str, float]:
    cost = np.asarray(state.cost)
    return {
        "start_cost_mean": float(cost[:, 0].mean()),
        "cost_mean": float(cost[:, 1].mean()),
        "compass_start_fraction": float((cost[:, 2] == 1).mean()),
        "valid_fraction_mean": float(cost[:, 3].mean()),
    }


def _measure(job: Job, state: State, steps: Steps) -> tuple[dict[str, Any], np.ndarray, dict] | None:
    """The measures against the ground truth (as ``metrics.json``), the true camera-to-world poses
    ``[M,4,4]`` and the aligned curves for the top view; ``None`` without ground truth of every frame."""
    truth = job.ride.ground_truth()
    if truth is None:
        return None
    times, gt = truth
    if len(gt) != len(state.stems):
        return None
    named = {
        "bundle adjusted": steps.adjusted,
        "loops closed": steps.closed,
        "steady height": steps.steady,
        "refined": steps.refined,
        "network": steps.network,
        "compass": steps.compass,
    }
    metrics, curves = ride_metrics(times, gt, named)
    return metrics, gt, curves
