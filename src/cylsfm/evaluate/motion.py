"""Does a pose estimate measure the motion, or emit a prior?  Diagnostics computed on every pose evaluation.

A pose network trained on rides that always go forward can score like "one usual step forward" without
looking at its input (RESULTS.md). These measures tell the two apart; each compares the estimate with
something whose answer is known:

- **turns**: on the consecutive steps whose true yaw exceeds :data:`TURN_DEG` degrees (*turning steps*),
  the least-squares slope through the origin of the predicted yaw against the true yaw (1: right, 0: never
  turns) and their correlation; and the rotation error per step in degrees (angle of ``R_pred^T R_true``),
  over all steps and over the turning ones;
- **a standing camera**: the sources replaced by the target itself (true motion zero); the median predicted
  translation relative to the median translation of the real windows (the usual step): 0 is right, about 1
  means the step comes from the network's bias;
- **swapped sources**: the sources in reverse order; for each source image the cosine between its
  translation in the other slot and in its own slot (+1: the prediction follows the image; -1: it follows
  the slot, i.e. the network has learned a motion per slot);
- **forward / backward**: ``T_{b->a} @ T_{a->b}`` for consecutive frames (``T_{a->b}`` from the window
  centred on ``a``, ``T_{b->a}`` from the one centred on ``b``) should be the identity: its translation
  relative to the usual step and its rotation angle in degrees (medians).

All poses are 4x4 NumPy arrays (float64), relative ``T_{a->b}`` with ``p_b = T p_a``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "MEASURED",
    "MOTION_COLUMNS",
    "TURN_DEG",
    "MotionRecord",
    "format_motion_table",
    "forward_backward",
    "motion_verdict",
    "rotation_error_deg",
    "standing_ratio",
    "steps_of",
    "swap_cosine",
    "turn_response",
    "verdict_line",
    "yaw_angle",
]

#: Steps turning by more than this many degrees (true yaw) are the *turning steps*.
TURN_DEG = 2.0

#: The bounds a measured ego-motion meets (the acceptance of the pose work): yaw slope on turning steps,
#: its correlation, a standing camera's step relative to the usual one, the swapped-source cosine, and the
#: forward/backward translation (relative to the usual step) and rotation (degrees).
MEASURED = {
    "yaw_slope": (0.7, 1.3),
    "yaw_correlation": (0.9, 1.0),
    "standing_ratio": (0.0, 0.25),
    "swap_cosine": (0.8, 1.0),
    "fb_trans_ratio": (0.0, 0.1),
    "fb_rot_deg": (0.0, 0.5),
}

#: Fewer turning steps than this say nothing about turns: no slope or correlation is reported.
MIN_TURNING = 5


def yaw_angle(poses: np.ndarray) -> np.ndarray:
    """The yaw (radians, about the vertical y axis) of rotations in poses ``[..., 4, 4]`` (or ``[..., 3, 3]``):
    ``atan2(R[0,2], R[2,2])``, the angle of :func:`cylsfm.geometry.rotation_y`."""
    poses = np.asarray(poses, dtype=np.float64)
    return np.arctan2(poses[..., 0, 2], poses[..., 2, 2])


def rotation_error_deg(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """The angle (degrees) of ``R_pred^T R_true`` for poses ``[..., 4, 4]``: ``[...]``."""
    r = np.swapaxes(np.asarray(pred)[..., :3, :3], -1, -2) @ np.asarray(true)[..., :3, :3]
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def turn_response(pred: np.ndarray, true: np.ndarray) -> dict[str, Any]:
    """How predicted steps ``[N,4,4]`` turn with the true ones ``[N,4,4]``.

    Returns:
        ``{"n_steps", "n_turning", "yaw_slope", "yaw_correlation", "rot_err_deg", "rot_err_deg_turning"}``:
        slope through the origin and correlation of the predicted against the true yaw on the turning
        steps (``None`` with fewer than :data:`MIN_TURNING` of them), mean rotation error per step
        (degrees) on all and on the turning steps.

    >>> from cylsfm.geometry import yaw_transform
    >>> true = np.stack([yaw_transform(math.radians(a), np.eye(4)) for a in (-6, -3, 0, 3, 6, 9, 12)])
    >>> half = np.stack([yaw_transform(math.radians(a / 2), np.eye(4)) for a in (-6, -3, 0, 3, 6, 9, 12)])
    >>> round(turn_response(half, true)["yaw_slope"], 6)
    0.5
    """
    pred_yaw, true_yaw = yaw_angle(pred), yaw_angle(true)
    turning = np.abs(true_yaw) > math.radians(TURN_DEG)
    err = rotation_error_deg(pred, true)
    out: dict[str, Any] = {
        "n_steps": len(true_yaw),
        "n_turning": int(turning.sum()),
        "yaw_slope": None,
        "yaw_correlation": None,
        "rot_err_deg": float(err.mean()) if len(err) else None,
        "rot_err_deg_turning": float(err[turning].mean()) if turning.any() else None,
    }
    if turning.sum() >= MIN_TURNING:
        p, t = pred_yaw[turning], true_yaw[turning]
        out["yaw_slope"] = float(np.dot(p, t) / np.dot(t, t))
        out["yaw_correlation"] = float(np.corrcoef(p, t)[0, 1]) if p.std() > 0 else 0.0
    return out


def _median_norm(poses: np.ndarray) -> float:
    return float(np.median(np.linalg.norm(np.asarray(poses)[..., :3, 3], axis=-1)))


def standing_ratio(standing: np.ndarray, real: np.ndarray) -> float | None:
    """Median translation predicted for a standing camera ``[N,4,4]`` over that of real windows ``[M,4,4]``
    (``None`` when the real step is zero)."""
    usual = _median_norm(real)
    return _median_norm(standing) / usual if usual > 0 else None


def swap_cosine(real: np.ndarray, swapped: np.ndarray) -> float:
    """Median cosine between each source's translation with the sources in order ``[N,S,4,4]`` and with
    them reversed (``swapped [N,S,4,4]``, put back in time order), over all windows and sources."""
    a, b = np.asarray(real)[..., :3, 3], np.asarray(swapped)[..., :3, 3]
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    cos = (a * b).sum(-1) / np.maximum(na * nb, 1e-12)
    cos = np.where((na > 0) & (nb > 0), cos, 0.0)
    return float(np.median(cos))


def forward_backward(ab: np.ndarray, ba: np.ndarray, usual_step: float) -> dict[str, float | None]:
    """``T_{b->a} @ T_{a->b}`` against the identity, for pairs ``ab, ba [N,4,4]``.

    Returns:
        ``{"fb_trans_ratio": median translation / usual_step, "fb_rot_deg": median rotation angle}``.
    """
    loop = np.asarray(ba) @ np.asarray(ab)
    trans = np.linalg.norm(loop[..., :3, 3], axis=-1)
    return {
        "fb_trans_ratio": float(np.median(trans)) / usual_step if usual_step > 0 else None,
        "fb_rot_deg": float(np.median(rotation_error_deg(loop, np.eye(4)))),
    }


def motion_verdict(diagnostics: dict[str, Any]) -> tuple[bool | None, list[str]]:
    """Whether diagnostics show a measured ego-motion (:data:`MEASURED`), with the checks it fails.

    Returns:
        ``(measured, failures)``: ``True`` when every available check passes, ``False`` otherwise; ``None``
        (nothing to judge) when no check is available. The turn checks are skipped when there were fewer
        than :data:`MIN_TURNING` turning steps (``yaw_slope`` is then ``None``).
    """
    failures, judged = [], 0
    for key, (lo, hi) in MEASURED.items():
        value = diagnostics.get(key)
        if value is None:
            continue
        judged += 1
        if not lo <= value <= hi:
            failures.append(f"{key} {value:.3g} outside [{lo:g}, {hi:g}]")
    return (None if judged == 0 else not failures), failures


def steps_of(c2w: np.ndarray) -> np.ndarray:
    """Consecutive relative poses ``T_{j->j+1} = inv(c2w_{j+1}) @ c2w_j`` ``[M-1,4,4]`` of camera-to-world
    poses ``[M,4,4]``."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return np.linalg.inv(c2w[1:]) @ c2w[:-1]


@dataclass
class MotionRecord:
    """The arrays the diagnostics need, gathered sequence by sequence (:meth:`add`), then summarised."""

    true: list[np.ndarray] = field(default_factory=list)
    model: list[np.ndarray] = field(default_factory=list)
    compass: list[np.ndarray] = field(default_factory=list)
    real: list[np.ndarray] = field(default_factory=list)
    standing: list[np.ndarray] = field(default_factory=list)
    swapped: list[np.ndarray] = field(default_factory=list)
    ab: list[np.ndarray] = field(default_factory=list)
    ba: list[np.ndarray] = field(default_factory=list)

    def add(
        self,
        true: np.ndarray,
        model: np.ndarray,
        compass: np.ndarray | None = None,
        windows: Any | None = None,
    ) -> None:
        """One sequence: true and estimated consecutive steps ``[N,4,4]`` (the same steps), the compass's
        (or ``None``: not a full panorama) and the network's :class:`~cylsfm.evaluate.pose_source.WindowPoses`
        (or ``None``: not a network)."""
        self.true.append(true)
        self.model.append(model)
        if compass is not None:
            self.compass.append(compass)
        if windows is not None and windows.standing:
            centres = sorted(windows.real)
            self.real.append(np.stack([windows.real[c] for c in centres]))
            self.standing.append(np.stack([windows.standing[c] for c in centres]))
            self.swapped.append(np.stack([windows.swapped[c] for c in centres]))
            ab, ba = windows.forward_backward_pairs()
            self.ab.append(ab)
            self.ba.append(ba)

    def summary(self) -> dict[str, Any]:
        """``{"turn_deg", "n_steps", "n_turning", "model", "compass", "constant_velocity", "verdict"}``: the
        diagnostics of the module docstring for the estimate, the compass (when every sequence had one) and
        constant velocity (no rotation, as zero motion), and :func:`motion_verdict` of the estimate."""
        true = np.concatenate(self.true) if self.true else np.zeros((0, 4, 4))
        model = turn_response(np.concatenate(self.model) if self.model else true, true)
        if self.real:
            real = np.concatenate(self.real)
            nxt = real.shape[1] // 2  # the source one frame after the target: the usual step
            standing = np.concatenate(self.standing)
            model["standing_ratio"] = standing_ratio(standing[:, nxt], real[:, nxt])
            model["swap_cosine"] = swap_cosine(real, np.concatenate(self.swapped))
            model.update(
                forward_backward(np.concatenate(self.ab), np.concatenate(self.ba), _median_norm(real[:, nxt]))
            )
        out: dict[str, Any] = {
            "turn_deg": TURN_DEG,
            "n_steps": model["n_steps"],
            "n_turning": model["n_turning"],
            "model": model,
            "compass": None,
            "constant_velocity": turn_response(np.tile(np.eye(4), (len(true), 1, 1)), true),
        }
        if self.compass and len(self.compass) == len(self.true):
            out["compass"] = turn_response(np.concatenate(self.compass), true)
        measured, failures = motion_verdict(model)
        out["verdict"] = {"measured": measured, "failures": failures}
        return out


#: The columns of the motion table: (key, header).
MOTION_COLUMNS = (
    ("yaw_slope", "yaw slope"),
    ("yaw_correlation", "yaw corr."),
    ("rot_err_deg", "rot. err"),
    ("rot_err_deg_turning", "rot. err turns"),
    ("standing_ratio", "standing/step"),
    ("swap_cosine", "swapped cos"),
    ("fb_trans_ratio", "fwd-bwd t/step"),
    ("fb_rot_deg", "fwd-bwd rot"),
)


def _bounds(key: str) -> str:
    lo, hi = MEASURED.get(key, (None, None))
    if lo is None:
        return ""
    return f"<= {hi:g}" if lo == 0 else (f">= {lo:g}" if hi == 1.0 else f"{lo:g}..{hi:g}")


def verdict_line(motion: dict[str, Any]) -> str:
    """One sentence: is the estimate's ego-motion measured or a prior (from ``motion["verdict"]``)?"""
    measured, failures = motion["verdict"]["measured"], motion["verdict"]["failures"]
    if measured is None:
        return "verdict: nothing to judge"
    if measured:
        return "verdict: MEASURED - the estimate turns with the camera and reads the motion from the images"
    return "verdict: NOT MEASURED - the estimate fails: " + "; ".join(failures)


def format_motion_table(motion: dict[str, Any]) -> str:
    """The diagnostics of a pose evaluation (``result["motion"]``) as a text table with the bounds a
    measured ego-motion meets and the verdict (rotation errors in degrees)."""
    from .tables import text_row

    widths = [max(10, len(h) + 2) for _, h in MOTION_COLUMNS]
    lines = [
        f"is the motion measured? {motion['n_steps']} consecutive steps, {motion['n_turning']} of them turning "
        f"(|true yaw| > {motion['turn_deg']:g} deg per frame)",
        text_row("", [h for _, h in MOTION_COLUMNS], widths, 19),
    ]
    rows = [("model", motion["model"]), ("compass", motion["compass"])]
    rows.append(("constant velocity", motion["constant_velocity"]))
    for name, values in rows:
        if values is not None:
            lines.append(text_row(name, [values.get(k) for k, _ in MOTION_COLUMNS], widths, 19))
    lines.append(text_row("measured if", [_bounds(k) for k, _ in MOTION_COLUMNS], widths, 19))
    if motion["n_turning"] < MIN_TURNING:
        lines.append(f"(fewer than {MIN_TURNING} turning steps: the turn columns say nothing)")
    lines.append(verdict_line(motion))
    return "\n".join(lines)
