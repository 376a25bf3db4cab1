"""Matches between the frames of a ride, guided by its odometry, and the tracks they make.

Two frames' keypoints are matched by their descriptors (the nearest neighbour, clearly nearer than the
second: Lowe's ratio, and mutual); a match is kept only when it fits the odometry's relative pose: its
two bearings lie on one epipolar plane (``b_j . (t x R b_i) = 0`` for ``p_j = R p_i + t``), to within an
angle, which holds across the seam and behind the camera alike. A camera that barely moved has no
epipolar plane: its matches must then agree with the rotation alone. Matches chain into tracks (a
union of every pair's matches); a track that would see two keypoints of one frame is dropped.

The odometry's relative pose is good enough to guide the matches (a match that fits it to 2 degrees), not
to start a bundle adjustment from: a few degrees off a step near the start of a ride leave the adjustment
in a wrong minimum. :func:`relative_pose` corrects it from the pair's own matches (the rotation and the
direction of travel that put them on their epipolar planes, robustly), keeping the odometry's step length,
which two views cannot see.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .adjust import Observations
from .features import Features

__all__ = ["epipolar_angles", "match_pair", "relative_pose", "tracks_of"]


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
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    with torch.inference_mode():  # every descriptor distance at once (a matrix product)
        dist = torch.cdist(torch.from_numpy(a.descriptors)[None], torch.from_numpy(b.descriptors)[None])[0]
        best, nearest = dist.topk(2, dim=1, largest=False)  # [Ka,2]
        back = dist.argmin(dim=0)  # [Kb]: each of b's nearest in a
    rows = torch.arange(len(a))
    keep = (best[:, 0] < ratio * best[:, 1]) & (back[nearest[:, 0]] == rows)
    if not bool(keep.any()):
        return np.zeros((0, 2), dtype=np.int64)
    found = torch.stack([rows[keep], nearest[keep, 0]], 1).numpy().astype(np.int64)
    angles = epipolar_angles(bearings_a[found[:, 0]], bearings_b[found[:, 1]], rel)
    return found[angles <= math.radians(max_angle_deg)]


def relative_pose(b_i: np.ndarray, b_j: np.ndarray, rel: np.ndarray, scale: float) -> np.ndarray:
    """The relative pose ``T_{i->j}`` ``[4,4]`` that best puts matched bearings ``b_i [K,3]``, ``b_j [K,3]``
    on their epipolar planes, starting from ``rel`` ``[4,4]`` (the odometry's) and keeping its translation's
    length.

    The rotation and the direction of the translation (5 degrees of freedom) minimise the matches' angles off
    their epipolar planes under a Cauchy loss of scale ``scale`` (radians), so that a wrong match weighs
    little; then again without the matches more than three times ``scale`` off. A translation of (almost)
    nothing has no direction to find: the rotation alone is then fitted to
    ``b_j = R b_i``.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    rot0, t0 = rel[:3, :3], rel[:3, 3]
    length = float(np.linalg.norm(t0))
    if len(b_i) == 0:
        return rel.copy()
    if length < 1e-9:

        def turned(x: np.ndarray) -> np.ndarray:
            rot = Rotation.from_rotvec(x).as_matrix() @ rot0
            return (b_j - b_i @ rot.T).ravel()

        x = least_squares(turned, np.zeros(3), loss="cauchy", f_scale=scale).x
        out = rel.copy()
        out[:3, :3] = Rotation.from_rotvec(x).as_matrix() @ rot0
        return out
    d0 = t0 / length
    e1 = np.cross(d0, [0.0, 1.0, 0.0]) if abs(d0[1]) < 0.9 else np.cross(d0, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d0, e1)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = d0 + x[3] * e1 + x[4] * e2
        return Rotation.from_rotvec(x[:3]).as_matrix() @ rot0, t / np.linalg.norm(t)

    def off_plane(x: np.ndarray) -> np.ndarray:
        rot, t = unpack(x)
        normal = np.cross(t, b_i @ rot.T)
        return np.einsum("ki,ki->k", normal, b_j) / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)

    x = least_squares(off_plane, np.zeros(5), loss="cauchy", f_scale=scale).x
    near = np.abs(off_plane(x)) < 3.0 * scale
    if 8 <= near.sum() < len(near):  # again without the matches that clearly disagree
        b_i, b_j = b_i[near], b_j[near]
        x = least_squares(off_plane, x, loss="cauchy", f_scale=scale).x
    rot, t = unpack(x)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, t * length
    return out


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
