"""Loop closure in :func:`cylsfm.odometry`: a tracked ride's loops found, verified and kept in its state
(:mod:`~cylsfm.odometry.loops` does the work), and what was found, as ``odometry.json`` says it."""

from __future__ import annotations

import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import CylsfmError
from ..evaluate.motion import yaw_angle
from ..evaluate.pose_metrics import chain_poses
from ..geometry import invert
from ..model import Predictor
from ..model.plan import network_images
from ..runtime import fingerprint
from .frames import Ride
from .loops import Loop, check_loops, loop_candidates, loop_rows, loops_from_rows, verify_loops
from .posegraph import close_loops
from .settings import OdometrySettings
from .state import STATE_FILE, State
from .track import Timings, Tracker, keyframe_steps, network_size

__all__ = ["closed_steps", "loop_line", "loop_summary_of", "ride_loops"]


def ride_loops(
    ride: Ride,
    plan: Any,
    predictor: Predictor,
    tracker: Tracker,
    state: State,
    opt: OdometrySettings,
    dest: Path,
) -> list[Loop]:
    """The ride's loops, found and verified once for the loop settings of ``opt`` (then kept in ``state``,
    saved in ``dest``; other loop settings verify again, on the same tracking)."""
    key = fingerprint(asdict(opt.loop))
    if state.loops is not None and state.loop_key == key:
        return loops_from_rows(state.loops, state.loop_why)
    t = time.perf_counter()
    steps = keyframe_steps(np.stack(state.refined), tracker.every) if opt.refine else np.stack(state.net)
    c2w = chain_poses(steps)
    reach = np.asarray(state.reach, dtype=np.float64)
    known = np.isfinite(reach)
    fallback = 10 * float(np.median(np.linalg.norm(steps[:, :3, 3], axis=1)))  # no depth: ~ten steps
    reach = np.where(known, reach, float(np.median(reach[known])) if known.any() else fallback)
    pairs = loop_candidates(torch.from_numpy(np.stack(state.places)), opt.loop, c2w, reach)
    wanted = {i for i, _, _ in pairs} | {j for _, j, _ in pairs}
    images: dict[int, torch.Tensor] = {}
    for i, rgb in ride.pick(wanted):
        x = network_size(network_images([rgb], plan, predictor.device), predictor.size)[0]
        images[i] = x.cpu()
    missing = wanted - images.keys()
    if missing:
        raise CylsfmError(f"{ride.path}: frames {sorted(missing)[:5]} could not be read again for the loops")
    depth = tracker.depths_of(sorted(wanted), images)
    views = {i: tracker.view_of(x) for i, x in images.items()}
    found = verify_loops(
        pairs, views.__getitem__, depth.__getitem__, tracker.view, opt.loop, mask=tracker.view_mask(), c2w=c2w
    )
    found = check_loops(found, c2w, reach, opt.loop)
    state.loops, state.loop_why, state.loop_key = loop_rows(found), [lp.why for lp in found], key
    state.save(dest / STATE_FILE)
    tracker.times.add("loops", t)
    return found


def loop_summary_of(loops: list[Loop] | None) -> dict[str, Any] | None:
    """What the loop closure found (``None``: not looked for): per verified pair its frames, whether it was
    accepted (and why not), the inlier fraction, the yaw, the scale ratio and the relative pose ``T_{i->j}``
    (16 numbers, row by row; translation in frame ``i``'s depth unit)."""
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
                "why": lp.why,
                "inliers": lp.inliers,
                "yaw_deg": math.degrees(float(yaw_angle(lp.pose))),
                "scale_ratio": lp.ratio,
                "pose": [round(float(v), 6) for v in lp.pose.ravel()],
            }
            for lp in loops
        ],
    }


def closed_steps(steps: np.ndarray, loops: list[Loop] | None, times: Timings) -> np.ndarray | None:
    """The steps ``[M-1,4,4]`` of the ride closed by its accepted loops (:func:`close_loops`), or ``None``
    when none was accepted; the pose graph's time goes to ``times``."""
    accepted = [lp for lp in loops or [] if lp.accepted]
    if not accepted:
        return None
    t = time.perf_counter()
    c2w, _ = close_loops(steps, accepted)
    times.add("pose graph", t)
    return np.stack([invert(c2w[j + 1]) @ c2w[j] for j in range(len(c2w) - 1)])


def loop_line(summary: dict[str, Any]) -> str:
    """The trajectory file's header line on the loops."""
    line = f"loops: {summary['verified']} candidate pairs verified, {summary['accepted']} accepted"
    return line + (" (closed by a pose graph)" if summary["accepted"] else "")
