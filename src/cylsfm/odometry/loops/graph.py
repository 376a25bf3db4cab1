"""Loop closure, the pose graph: the whole ride's poses optimised together with the loops (GTSAM).

Every frame is a node, a similarity transform ``X_j`` (rotation, position and scale: a point ``p`` of
frame ``j``, in that frame's depth unit, is at ``s_j (R_j p + t_j)`` in the world), so that the
monocular scale may drift along the ride and a loop can correct it. The factors:

- the first frame fixed at the identity;
- one between consecutive frames from odometry's step ``T_{j->j+1}`` (``p_{j+1} = T p_j``): the relative
  similarity ``X_j^-1 X_{j+1} = inv(T)`` with scale 1, rotation trusted to a degree, translation to a
  tenth of the median step, the scale to half a per cent a step (the drift allowed; chosen on rides of
  training towns, see RESULTS.md);
- one per accepted loop ``(i, j)`` from its pose ``T_{i->j}`` and the ratio of the two frames' depth units,
  under a Huber kernel, so that a wrong loop that slipped through the verification costs little once it
  disagrees with the rest, instead of folding the trajectory onto it; a loop still more than
  :attr:`GraphSettings.reject` standard deviations off after solving is dropped and the graph solved again.

Levenberg-Marquardt from the odometry's chained poses. The result is in the first frame's unit (the
odometry's unit where it starts).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...evaluate.pose_metrics import chain_poses
from ...geometry import invert
from .loop import Loop

__all__ = ["GraphSettings", "close_loops", "closed_steps"]


@dataclass(frozen=True)
class GraphSettings:
    """The uncertainties of the pose graph's factors (standard deviations).

    Attributes:
        step_rotation_deg: an odometry step's rotation.
        step_translation: an odometry step's translation, as a fraction of the median step length.
        step_scale: the change of scale over one step (log).
        loop_rotation_deg, loop_translation, loop_scale: the same for a loop (translation as a fraction of
            the median step length).
        huber: the Huber kernel's threshold on loop factors, in standard deviations.
        reject: after solving, a loop whose error is larger than this many standard deviations (the norm
            of its whitened error) is dropped and the graph solved again (twice at most).
        iterations: Levenberg-Marquardt iterations at most.
    """

    step_rotation_deg: float = 1.0
    step_translation: float = 0.1
    step_scale: float = 0.005
    loop_rotation_deg: float = 1.0
    loop_translation: float = 0.3
    loop_scale: float = 0.05
    huber: float = 3.0
    reject: float = 10.0
    iterations: int = 100


def _similarity(gtsam, pose: np.ndarray, scale: float = 1.0):
    """A 4x4 rigid ``[R t; 0 1]`` and a scale -> gtsam's ``Similarity3`` acting as ``scale (R p + t)``."""
    return gtsam.Similarity3(gtsam.Rot3(pose[:3, :3]), np.asarray(pose[:3, 3], dtype=np.float64), scale)


def _sigmas(rotation_deg: float, translation: float, scale: float) -> np.ndarray:
    """gtsam's Similarity3 tangent order: rotation (3), translation (3), log scale (1)."""
    return np.array([np.radians(rotation_deg)] * 3 + [translation] * 3 + [scale], dtype=np.float64)


def _loop_measure(gtsam, lp: Loop):
    """A loop's measured ``X_i^-1 X_j``: frame ``j``'s points (its unit) to frame ``i``'s,
    ``p_i = (1/ratio)(R^T p_j - ratio R^T t)``."""
    rot_t = lp.pose[:3, :3].T
    rel = np.eye(4)
    rel[:3, :3] = rot_t
    rel[:3, 3] = -lp.ratio * rot_t @ lp.pose[:3, 3]
    return _similarity(gtsam, rel, 1.0 / lp.ratio)


def _loop_error(values, lp: Loop, unit: float, cfg: GraphSettings) -> float:
    """The norm of a loop's whitened error at ``values``."""
    import gtsam

    between = values.atSimilarity3(lp.i).between(values.atSimilarity3(lp.j))
    err = gtsam.Similarity3.Logmap(_loop_measure(gtsam, lp).between(between))
    return float(
        np.linalg.norm(err / _sigmas(cfg.loop_rotation_deg, cfg.loop_translation * unit, cfg.loop_scale))
    )


def _graph(
    gtsam,
    steps: np.ndarray,
    loops: list[Loop],
    unit: float,
    cfg: GraphSettings,
    step_scale: float,
    loop_scale: float,
):
    """The factor graph (see the module docstring), with these scale uncertainties."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorSimilarity3(0, gtsam.Similarity3(), gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)))
    odo = gtsam.noiseModel.Diagonal.Sigmas(
        _sigmas(cfg.step_rotation_deg, cfg.step_translation * unit, step_scale)
    )
    for j, step in enumerate(steps):
        graph.add(gtsam.BetweenFactorSimilarity3(j, j + 1, _similarity(gtsam, invert(step)), odo))
    loop_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber),
        gtsam.noiseModel.Diagonal.Sigmas(
            _sigmas(cfg.loop_rotation_deg, cfg.loop_translation * unit, loop_scale)
        ),
    )
    for lp in loops:
        graph.add(gtsam.BetweenFactorSimilarity3(lp.i, lp.j, _loop_measure(gtsam, lp), loop_noise))
    return graph


def close_loops(
    steps: np.ndarray, loops: list[Loop], settings: GraphSettings | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Optimise a ride's poses with its accepted loops (see the module docstring).

    Args:
        steps: odometry's consecutive steps ``T_{j->j+1}`` ``[M-1,4,4]``.
        loops: verified loops (only the accepted ones are used).
        settings: the factors' uncertainties.

    Returns:
        ``(c2w [M,4,4], scales [M])``: the camera-to-world poses (positions in the first frame's unit)
        and each frame's scale relative to the first (how much the odometry's unit drifted there).
        Without an accepted loop, the steps chained and scales 1.
    """
    import gtsam

    cfg = settings or GraphSettings()
    steps = np.asarray(steps, dtype=np.float64)
    m = len(steps) + 1
    accepted = [lp for lp in loops if lp.accepted]
    start = chain_poses(steps)
    if not accepted:
        return start, np.ones(m)
    unit = float(np.median(np.linalg.norm(steps[:, :3, 3], axis=1))) or 1.0
    values = gtsam.Values()
    for j in range(m):
        values.insert(j, _similarity(gtsam, start[j]))
    # first with the scale held (a rigid pose graph: far from its optimum a free scale wanders off), then
    # with the scale free to drift, from there; loops that still disagree with the rest by more than
    # ``cfg.reject`` standard deviations are dropped and the graph solved again without them
    for _ in range(3):
        for step_scale, loop_scale in ((1e-4, 1e-4), (cfg.step_scale, cfg.loop_scale)):
            graph = _graph(gtsam, steps, accepted, unit, cfg, step_scale, loop_scale)
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(cfg.iterations)
            values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        errors = [_loop_error(values, lp, unit, cfg) for lp in accepted]
        keep = [lp for lp, e in zip(accepted, errors, strict=True) if e <= cfg.reject]
        if len(keep) == len(accepted) or not keep:
            break
        accepted = keep
    result = values
    c2w = np.tile(np.eye(4), (m, 1, 1))
    scales = np.ones(m)
    for j in range(m):
        x = result.atSimilarity3(j)
        c2w[j, :3, :3] = x.rotation().matrix()
        c2w[j, :3, 3] = x.scale() * np.asarray(x.translation())
        scales[j] = x.scale()
    return c2w, scales


def closed_steps(steps: np.ndarray, loops: list[Loop] | None) -> np.ndarray | None:
    """The steps ``[M-1,4,4]`` of the ride closed by its accepted loops (:func:`close_loops`), or ``None``
    when none was accepted."""
    if not any(lp.accepted for lp in loops or []):
        return None
    c2w, _ = close_loops(steps, list(loops or []))
    return np.stack([invert(c2w[j + 1]) @ c2w[j] for j in range(len(c2w) - 1)])
