"""Matches between the frames of a ride, guided by its odometry, and the tracks they make.

Two frames' keypoints are matched by their descriptors (the nearest neighbour, clearly nearer than the
second: Lowe's ratio, and mutual); a match is kept only when it fits the odometry's relative pose: its
two bearings lie on one epipolar plane (``b_j . (t x R b_i) = 0`` for ``p_j = R p_i + t``), to within an
angle, which holds across the seam and behind the camera alike. A camera that barely moved has no
epipolar plane: its matches must then agree with the rotation alone. Matches chain into tracks (a
union of every pair's matches); a track that would see two keypoints of one frame is dropped.
"""

from __future__ import annotations

import math

import numpy as np

from .adjust import Observations
from .features import Features

__all__ = ["epipolar_angles", "match_pair", "tracks_of"]


def epipolar_angles(b_i: np.ndarray, b_j: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """The angle (radians) of each bearing ``b_j [K,3]`` off the epipolar plane of its ``b_i [K,3]`` under
    ``rel`` ``T_{i->j}`` ``[4,4]`` (``p_j = R p_i + t``); for a translation of (almost) nothing, the angle
    between ``b_j`` and ``R b_i``."""
    rot, t = rel[:3, :3], rel[:3, 3]
    turned = b_i @ rot.T
    length = float(np.linalg.norm(t))
    if length < 1e-9:
        return np.arccos(np.clip(np.einsum("ki,ki->k", turned, b_j), -1.0, 1.0))
    normal = np.cross(t / length, turned)
    size = np.linalg.norm(normal, axis=1)
    sine = np.abs(np.einsum("ki,ki->k", normal, b_j)) / np.where(size > 1e-12, size, 1.0)
    return np.where(size > 1e-12, np.arcsin(np.clip(sine, 0.0, 1.0)), 0.0)


def match_pair(
    a: Features,
    b: Features,
    bearings_a: np.ndarray,
    bearings_b: np.ndarray,
    rel: np.ndarray,
    ratio: float = 0.8,
    max_angle_deg: float = 2.0,
) -> np.ndarray:
    """Matches ``[K,2]`` (index into ``a``, index into ``b``) between two frames' features whose bearings
    are ``bearings_a [Ka,3]``, ``bearings_b [Kb,3]``, guided by the odometry's ``rel`` ``T_{a->b}``."""
    import cv2

    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    backward = {
        m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(b.descriptors, a.descriptors, k=1) if m
    }
    pairs = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in forward
        if len(m) == 2
        and m[0].distance < ratio * m[1].distance
        and backward.get(m[0].trainIdx) == m[0].queryIdx
    ]
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    found = np.array(pairs, dtype=np.int64)
    angles = epipolar_angles(bearings_a[found[:, 0]], bearings_b[found[:, 1]], rel)
    return found[angles <= math.radians(max_angle_deg)]


def tracks_of(matches: dict[tuple[int, int], np.ndarray], bearings: list[np.ndarray]) -> Observations:
    """The observations of the tracks that the matches make.

    Args:
        matches: ``{(i, j): [K,2]}``: keypoint ``k`` of frame ``i`` is keypoint ``l`` of frame ``j``.
        bearings: each frame's keypoints' bearings ``[Ki,3]``.

    Returns:
        One observation per keypoint of every track that sees at least two frames, each frame once.
    """
    offsets = np.concatenate([[0], np.cumsum([len(b) for b in bearings])]).astype(np.int64)
    parent = np.arange(offsets[-1])

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for (i, j), pairs in matches.items():
        for k, l in pairs.tolist():
            ra, rb = root(offsets[i] + k), root(offsets[j] + l)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([root(x) for x in range(len(parent))], dtype=np.int64)
    frame_of = np.repeat(np.arange(len(bearings)), np.diff(offsets))
    sizes = np.bincount(roots, minlength=len(parent))
    # a track with two keypoints of one frame is a contradiction: dropped whole
    pair_keys = roots * len(bearings) + frame_of
    repeated = np.zeros(len(parent), dtype=bool)
    uniq, counts = np.unique(pair_keys, return_counts=True)
    repeated[uniq[counts > 1] // len(bearings)] = True
    keep = (sizes[roots] >= 2) & ~repeated[roots]
    ids = np.unique(roots[keep])
    point = np.searchsorted(ids, roots[keep])
    all_bearings = np.concatenate(bearings) if bearings else np.zeros((0, 3))
    return Observations(frame_of[keep], point, all_bearings[keep], np.nonzero(keep)[0])
