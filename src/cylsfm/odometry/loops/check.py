"""Loop closure, the checks against the odometry: streets that only look alike are told apart by the
odometry's own poses. A verified loop must lie within the odometry's plausible drift (position and
heading, :class:`~cylsfm.odometry.loops.settings.LoopSettings` ``max_drift`` and the yaw drift), and other
verified loops nearby must agree with it through the odometry between them (``support``): a revisit is
seen by several consecutive frames, a lookalike rarely agrees with itself."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ...evaluate.motion import yaw_angle
from ...geometry import invert
from .loop import Loop, Reason, odometry_yaw, rotation_deg
from .settings import LoopSettings

__all__ = ["check_loops"]


def check_loops(loops: list[Loop], c2w: np.ndarray, reach: np.ndarray, settings: LoopSettings) -> list[Loop]:
    """The verified loops checked against the odometry: the same loops, those that fail a check no longer
    accepted (their :attr:`~Loop.reason` names the check).

    Args:
        loops: from :func:`~cylsfm.odometry.loops.verify.verify_loops`.
        c2w: the odometry's camera-to-world poses ``[M,4,4]`` (its own unit).
        reach: each frame's median depth ``[M]`` (the same unit).
    """
    pos = c2w[:, :3, 3]
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    reasons = [lp.reason for lp in loops]
    supporters: list[int] = []
    for n, lp in enumerate(loops):
        weak = (
            lp.reason is Reason.FEW_INLIERS
            and lp.inliers >= settings.min_inliers_support
            and abs(float(yaw_angle(lp.pose))) <= math.radians(settings.turned_deg)
        )
        if not (lp.accepted or weak):
            continue
        beyond = _beyond_drift(lp, c2w, reach, travelled[lp.j] - travelled[lp.i], settings)
        if beyond is not None and lp.accepted:
            reasons[n] = beyond
        if beyond is None:
            supporters.append(n)
    for n, a in enumerate(loops):
        if reasons[n] is not Reason.ACCEPTED:
            continue
        agree = sum(
            1
            for m in supporters
            if abs(a.i - loops[m].i) <= settings.span
            and abs(a.j - loops[m].j) <= settings.span
            and (m == n or _agree(a, loops[m], c2w, reach))
        )
        if agree < settings.support:
            reasons[n] = Reason.UNSUPPORTED
    return [lp if r is lp.reason else replace(lp, reason=r) for lp, r in zip(loops, reasons, strict=True)]


def _beyond_drift(
    lp: Loop, c2w: np.ndarray, reach: np.ndarray, travelled: float, settings: LoopSettings
) -> Reason | None:
    """Which drift loop ``lp`` asks for more than the odometry can plausibly have (``None``: neither);
    ``travelled``: the odometry's way between its two frames."""
    odo = invert(c2w[lp.j]) @ c2w[lp.i]  # the odometry's T_{i->j}
    centre_loop = -lp.pose[:3, :3].T @ lp.pose[:3, 3]  # camera j in frame i
    centre_odo = -odo[:3, :3].T @ odo[:3, 3]
    if np.linalg.norm(centre_loop - centre_odo) > settings.max_drift * travelled + 0.1 * reach[lp.i]:
        return Reason.BEYOND_DRIFT
    turn = float(yaw_angle(lp.pose)) - odometry_yaw(c2w, lp.i, lp.j)
    if abs(math.remainder(turn, 2 * math.pi)) > settings.yaw_allowance(lp.i, lp.j):
        return Reason.TURNED_BEYOND_DRIFT
    return None


def _agree(a: Loop, b: Loop, c2w: np.ndarray, reach: np.ndarray) -> bool:
    """Whether loop ``b``'s pose is what loop ``a``'s predicts through the odometry between their frames
    (``T_{ib->jb} ≈ T_{ja->jb} T_{ia->ja} T_{ib->ia}``): within 3 degrees and a tenth of the median depth
    plus a tenth of the odometry's way between them."""

    def odo(x: int, y: int) -> np.ndarray:  # the odometry's T_{x->y}
        return invert(c2w[y]) @ c2w[x]

    pred = odo(a.j, b.j) @ a.pose @ odo(b.i, a.i)
    way = np.linalg.norm(odo(a.j, b.j)[:3, 3]) + np.linalg.norm(odo(b.i, a.i)[:3, 3])
    rot = rotation_deg(pred[:3, :3].T @ b.pose[:3, :3])
    return rot <= 3.0 and np.linalg.norm(pred[:3, 3] - b.pose[:3, 3]) <= 0.1 * (reach[b.i] + way)
