"""Loop closure, candidates: the pairs of frames a ride may come back to, by their place descriptors.

Every frame has a heading-invariant descriptor (:func:`~cylsfm.geometry.place.place_descriptor`).
Distances between frames far apart in time are averaged along short sequences (the frames around each,
matched in the same order for a revisit in the same direction and in reverse order for one in the
opposite direction), which tells a street passed before from one that merely looks like it far better
than one frame does. Each query frame keeps its few nearest earlier frames (at least ``min_gap`` frames
back, within the odometry's plausible drift when its poses are given); the pairs are ranked by their
distance relative to the query's median, and the best ones go on to the verification
(:mod:`~cylsfm.odometry.loops.verify`).
"""

from __future__ import annotations

import numpy as np
from torch import Tensor

from ...geometry.place import place_distance
from .settings import LoopSettings

__all__ = ["loop_candidates", "sequence_distances"]


def sequence_distances(desc: Tensor, window: int, rows: tuple[int, int] | None = None) -> np.ndarray:
    """Descriptor distances ``[R,N]`` averaged over ``2 * window + 1`` frames: for each pair the smaller
    of the same-order average (``d(i+t, j+t)``) and the reverse-order one (``d(i+t, j-t)``), over the
    frames that exist.

    Args:
        desc: the frames' descriptors ``[N,D]``.
        window: frames on each side.
        rows: the query frames ``[a, b)`` whose rows are wanted (``R = b - a``); ``None``: all (``R = N``).
            Only ``R + 2 * window`` rows of plain distances are held at once, so a long ride is searched
            a block of rows at a time.
    """
    n = desc.shape[0]
    a, b = (0, n) if rows is None else rows
    lo, hi = max(0, a - window), min(n, b + window)
    d = np.full((b - a + 2 * window, n + 2 * window), np.nan)  # rows a-w .. b+w, columns -w .. n+w
    d[lo - a + window : hi - a + window, window : window + n] = (
        place_distance(desc[lo:hi], desc).double().numpy()
    )
    if window == 0:
        return d[:, :n]
    best = np.full((b - a, n), np.inf)
    for sign in (1, -1):
        total, count = np.zeros_like(best), np.zeros_like(best)
        for t in range(-window, window + 1):
            part = d[window + t : window + t + b - a, window + sign * t : window + sign * t + n]
            total += np.nan_to_num(part)
            count += ~np.isnan(part)
        best = np.minimum(best, total / np.maximum(count, 1))
    return best


def loop_candidates(
    desc: Tensor,
    settings: LoopSettings,
    c2w: np.ndarray | None = None,
    reach: np.ndarray | None = None,
) -> list[tuple[int, int, float]]:
    """Pairs ``(i, j, relative distance)`` (``i <= j - min_gap``) to verify, best first, at most
    ``max_pairs`` (see the module docstring).

    Args:
        desc: the frames' descriptors ``[N,D]``.
        settings: the search's settings.
        c2w, reach: the odometry's poses ``[N,4,4]`` and the frames' median depths ``[N]``: with them, only
            the earlier frames within the odometry's plausible drift of the query
            (:attr:`LoopSettings.max_drift`) are considered.
    """
    n = desc.shape[0]
    if n <= settings.min_gap:
        return []
    block, dist, first = 256, np.empty((0, n)), 0  # query rows [first, first + len(dist)) held
    gated = c2w is not None and reach is not None
    if gated:
        pos = c2w[:, :3, 3]
        travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    pairs = []
    for j in range(settings.min_gap, n):
        if j >= first + len(dist):
            first = j
            dist = sequence_distances(desc, settings.window, (j, min(n, j + block)))
        m = j - settings.min_gap + 1
        earlier = dist[j - first, :m]
        median = float(np.median(earlier))  # the query's typical distance, over every earlier frame
        plausible = np.ones(m, dtype=bool)
        if gated:  # one row at a time: no N x N matrices of positions
            apart = np.linalg.norm(pos[:m] - pos[j], axis=-1)
            plausible = apart <= settings.max_drift * (travelled[j] - travelled[:m]) + 0.1 * reach[:m]
        taken: list[int] = []
        for i in np.argsort(earlier, kind="stable"):
            if not plausible[i]:
                continue
            if all(abs(int(i) - t) > settings.window for t in taken):
                taken.append(int(i))
                pairs.append((int(i), j, float(earlier[i]) / max(median, 1e-12)))
            if len(taken) == settings.per_query:
                break
    pairs.sort(key=lambda p: p[2])
    return pairs[: settings.max_pairs]
