"""How the odometry's saved state keeps verified loops: named NumPy arrays (no pickles), one row a loop."""

from __future__ import annotations

import numpy as np

from .loop import Loop, Reason

__all__ = ["loops_from_arrays", "loops_to_arrays"]


def loops_to_arrays(loops: list[Loop]) -> dict[str, np.ndarray]:
    """Loops ``[K]`` as arrays: ``frames [K,2]`` (``i, j``), ``poses [K,4,4]``, ``ratio``, ``inliers``,
    ``distance [K]``, ``disagreement [K,2]`` and ``reason [K]`` (:class:`Reason` codes)."""
    k = len(loops)
    return {
        "frames": np.array([(lp.i, lp.j) for lp in loops], dtype=np.int64).reshape(k, 2),
        "poses": np.array([lp.pose for lp in loops], dtype=np.float64).reshape(k, 4, 4),
        "ratio": np.array([lp.ratio for lp in loops], dtype=np.float64),
        "inliers": np.array([lp.inliers for lp in loops], dtype=np.float64),
        "distance": np.array([lp.distance for lp in loops], dtype=np.float64),
        "disagreement": np.array([lp.disagreement for lp in loops], dtype=np.float64).reshape(k, 2),
        "reason": np.array([lp.reason.value for lp in loops], dtype=str),
    }


def loops_from_arrays(arrays: dict[str, np.ndarray]) -> list[Loop]:
    """The inverse of :func:`loops_to_arrays`.

    Raises:
        ValueError, KeyError: arrays that do not hold loops (an unknown reason, ragged columns).
    """
    frames, poses = np.asarray(arrays["frames"]), np.asarray(arrays["poses"], dtype=np.float64)
    k = len(frames)
    columns = [arrays[name] for name in ("ratio", "inliers", "distance", "disagreement", "reason")]
    if frames.shape != (k, 2) or poses.shape != (k, 4, 4) or any(len(c) != k for c in columns):
        raise ValueError("loops: columns of different lengths")
    ratio, inliers, distance, disagreement, reason = columns
    return [
        Loop(
            int(frames[n, 0]),
            int(frames[n, 1]),
            poses[n].copy(),
            float(ratio[n]),
            float(inliers[n]),
            (float(disagreement[n, 0]), float(disagreement[n, 1])),
            float(distance[n]),
            Reason(str(reason[n])),
        )
        for n in range(k)
    ]
