"""Rigid transforms: 6-DoF vectors, 4x4 matrices, quaternions (TUM order).

A *pose vector* is ``(tx, ty, tz, rx, ry, rz)``: a translation (metres, or the network's depth units) and a
rotation as an axis-angle vector ``omega`` (radians; the rotation is by ``|omega|`` about
``omega / |omega|``, right-handed). The matrix is ``T = [[R, t], [0, 1]]`` with ``R = exp([omega]_x)``
(Rodrigues), so ``T @ p = R p + t``. Axis-angle has no gimbal lock and is equivariant under a change of
frame: rotating a motion by ``Q`` maps ``(t, omega)`` to ``(Q t, Q omega)``.

Quaternions follow TUM files: ``(qx, qy, qz, qw)``, Hamilton convention, unit norm.

All functions accept any leading batch shape ``[...]``. The elementary rotations (:func:`rotation_x`,
:func:`rotation_y`, :func:`rotation_z`), :func:`invert` and :func:`yaw_transform` also take NumPy arrays and
then return NumPy arrays: the evaluation and the synthetic-scene generator use the same helpers.

>>> import math
>>> R = rotation_y(torch.tensor(math.pi / 2, dtype=torch.float64))
>>> (R @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).round(decimals=6)  # forward turns to the right
tensor([1., 0., 0.], dtype=torch.float64)
"""

from __future__ import annotations

from types import ModuleType
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor

from ..errors import check_shape

ArrayT = TypeVar("ArrayT", Tensor, np.ndarray)

__all__ = [
    "axis_angle_to_matrix",
    "compose",
    "invert",
    "mat_to_pose_vec",
    "mat_to_tum",
    "matrix_to_axis_angle",
    "matrix_to_quaternion",
    "pose_vec_to_mat",
    "quaternion_to_matrix",
    "relative_pose",
    "rotation_x",
    "rotation_y",
    "rotation_z",
    "tum_to_mat",
    "yaw_matrix",
    "yaw_transform",
]


def _xp(x: object) -> ModuleType:
    """The array library of ``x``: ``numpy`` for NumPy arrays, else ``torch``."""
    return np if isinstance(x, np.ndarray) else torch


def _rotation(angle: ArrayT, axis: int) -> ArrayT:
    xp = _xp(angle)
    c, s = xp.cos(angle), xp.sin(angle)
    z, o = xp.zeros_like(angle), xp.ones_like(angle)
    if axis == 0:
        rows = ((o, z, z), (z, c, -s), (z, s, c))
    elif axis == 1:
        rows = ((c, z, s), (z, o, z), (-s, z, c))
    else:
        rows = ((c, -s, z), (s, c, z), (z, z, o))
    return xp.stack([xp.stack(r, -1) for r in rows], -2)


def rotation_x(angle: ArrayT) -> ArrayT:
    """Rotation ``[..., 3, 3]`` by ``angle [...]`` radians about the x (right) axis: pitch."""
    return _rotation(angle, 0)


def rotation_y(angle: ArrayT) -> ArrayT:
    """Rotation ``[..., 3, 3]`` by ``angle [...]`` radians about the y (down) axis: yaw.

    Positive angles turn z (forward) towards x (right), i.e. increase azimuths ``atan2(x, z)``.
    """
    return _rotation(angle, 1)


def rotation_z(angle: ArrayT) -> ArrayT:
    """Rotation ``[..., 3, 3]`` by ``angle [...]`` radians about the z (forward) axis: roll."""
    return _rotation(angle, 2)


def _skew(w: Tensor) -> Tensor:
    """``[..., 3] -> [..., 3, 3]`` cross-product matrix."""
    zero = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack(
        (
            torch.stack((zero, -wz, wy), -1),
            torch.stack((wz, zero, -wx), -1),
            torch.stack((-wy, wx, zero), -1),
        ),
        -2,
    )


def axis_angle_to_matrix(omega: Tensor) -> Tensor:
    """Rodrigues' formula: axis-angle ``[..., 3]`` (radians) -> rotation matrix ``[..., 3, 3]``.

    Differentiable everywhere, including at ``omega = 0`` (Taylor expansions near zero).
    """
    theta2 = (omega * omega).sum(-1, keepdim=True)
    small = theta2 < 1e-8
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(theta2_safe)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2_safe)
    k = _skew(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(k)
    return eye + a.unsqueeze(-1) * k + b.unsqueeze(-1) * (k @ k)


def matrix_to_axis_angle(rot: Tensor) -> Tensor:
    """Rotation matrix ``[..., 3, 3]`` -> axis-angle ``[..., 3]`` with angle in ``[0, pi]``.

    Goes through the quaternion, which is numerically stable for all angles including ``pi``.
    """
    q = matrix_to_quaternion(rot)  # (x, y, z, w) with w >= 0
    vec = q[..., :3]
    sin_half = torch.linalg.vector_norm(vec, dim=-1, keepdim=True)
    half = torch.atan2(sin_half, q[..., 3:4])
    scale = torch.where(
        sin_half < 1e-8, 2.0 / q[..., 3:4].clamp(min=1e-8), 2 * half / sin_half.clamp(min=1e-12)
    )
    return vec * scale


def pose_vec_to_mat(vec: Tensor) -> Tensor:
    """Pose vector ``[..., 6]`` = (t, axis-angle) -> 4x4 transform ``[..., 4, 4]``.

    >>> T = pose_vec_to_mat(torch.tensor([1.0, 0.0, 0.0, 0.0, torch.pi / 2, 0.0]))
    >>> (T @ torch.tensor([0.0, 0.0, 1.0, 1.0])).round(decimals=5)  # turn right by 90 degrees, then move
    tensor([2., 0., 0., 1.])
    >>> torch.allclose(mat_to_pose_vec(T), torch.tensor([1.0, 0.0, 0.0, 0.0, torch.pi / 2, 0.0]))
    True
    """
    check_shape(vec, "*,6", "pose vectors (6 components)")
    rot = axis_angle_to_matrix(vec[..., 3:])
    top = torch.cat((rot, vec[..., :3].unsqueeze(-1)), -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat((top, bottom), -2)


def mat_to_pose_vec(mat: Tensor) -> Tensor:
    """4x4 transform ``[..., 4, 4]`` -> pose vector ``[..., 6]`` (inverse of :func:`pose_vec_to_mat`)."""
    return torch.cat((mat[..., :3, 3], matrix_to_axis_angle(mat[..., :3, :3])), -1)


def compose(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for transforms ``[..., 4, 4]``: apply ``b`` first, then ``a``."""
    return a @ b


def invert(mat: ArrayT) -> ArrayT:
    """Inverse of rigid transforms ``[..., 4, 4]`` (uses ``R^T``, no general matrix inverse).

    Tensors give tensors, NumPy arrays NumPy arrays.
    """
    xp = _xp(mat)
    rot_t = xp.swapaxes(mat[..., :3, :3], -1, -2)
    t = -(rot_t @ mat[..., :3, 3:4])
    out = xp.zeros_like(mat)
    out[..., :3, :3] = rot_t
    out[..., :3, 3:4] = t
    out[..., 3, 3] = 1
    return out


def relative_pose(c2w_target: Tensor, c2w_source: Tensor) -> Tensor:
    """``T_tgt_to_src = inv(c2w_source) @ c2w_target``: maps target-camera points into the source camera.

    ``c2w_*`` are camera-to-world transforms ``[..., 4, 4]`` as stored in TUM files.

    >>> target, source = torch.eye(4), torch.eye(4)
    >>> source[2, 3] = 1.0  # the source camera is one metre further forward
    >>> relative_pose(target, source)[:3, 3]  # so a target point is one metre closer to it
    tensor([ 0.,  0., -1.])
    """
    return invert(c2w_source) @ c2w_target


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Quaternion ``[..., 4]`` in TUM order ``(qx, qy, qz, qw)`` -> rotation ``[..., 3, 3]`` (normalised first)."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack(
        (
            torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)), -1),
            torch.stack((2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)), -1),
            torch.stack((2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)), -1),
        ),
        -2,
    )


def matrix_to_quaternion(rot: Tensor) -> Tensor:
    """Rotation ``[..., 3, 3]`` -> unit quaternion ``[..., 4]`` ``(qx, qy, qz, qw)`` with ``qw >= 0``.

    Picks, per matrix, the best-conditioned of the four standard formulas.
    """
    m = rot
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    # Four candidate (unnormalised) quaternions, each accurate when its leading term is large.
    cands = torch.stack(
        (
            torch.stack((m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1], 1 + trace), -1),
            torch.stack((1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] - m[..., 1, 2]), -1),
            torch.stack((m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1], m[..., 0, 2] - m[..., 2, 0]), -1),
            torch.stack((m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22, m[..., 1, 0] - m[..., 0, 1]), -1),
        ),
        -2,
    )  # fmt: skip
    lead = torch.stack((1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22), -1)
    best = lead.argmax(-1, keepdim=True)
    q = torch.gather(cands, -2, best.unsqueeze(-1).expand(*best.shape[:-1], 1, 4)).squeeze(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def tum_to_mat(tum: Tensor) -> Tensor:
    """TUM pose rows ``[..., 7]`` = ``(tx, ty, tz, qx, qy, qz, qw)`` -> transforms ``[..., 4, 4]``.

    (The leading timestamp of a TUM line is not part of ``tum``.)
    """
    check_shape(tum, "*,7", "TUM poses (7 values: tx ty tz qx qy qz qw)")
    rot = quaternion_to_matrix(tum[..., 3:])
    top = torch.cat((rot, tum[..., :3].unsqueeze(-1)), -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat((top, bottom), -2)


def mat_to_tum(mat: Tensor) -> Tensor:
    """Transforms ``[..., 4, 4]`` -> TUM pose rows ``[..., 7]`` = ``(tx, ty, tz, qx, qy, qz, qw)``."""
    return torch.cat((mat[..., :3, 3], matrix_to_quaternion(mat[..., :3, :3])), -1)


def yaw_matrix(angle: Tensor | float, dtype: torch.dtype = torch.float32) -> Tensor:
    """Rotation ``[..., 3, 3]`` by ``angle`` radians about the camera's vertical (y, down) axis.

    Positive angles turn the z (forward) axis towards x (right): ``R @ (0, 0, 1) = (sin a, 0, cos a)``,
    i.e. they increase the azimuth ``theta = atan2(x, z)`` of a point by ``a``.
    """
    return rotation_y(torch.as_tensor(angle, dtype=dtype))


def yaw_transform(angle: float, like: ArrayT) -> ArrayT:
    """The 4x4 rigid transform of :func:`yaw_matrix` (no translation), as ``like``'s kind and dtype.

    >>> yaw_transform(0.0, np.zeros(1)).tolist() == np.eye(4).tolist()
    True
    """
    xp = _xp(like)
    out = xp.eye(4, dtype=like.dtype)
    if xp is torch:
        out[:3, :3] = rotation_y(torch.tensor(float(angle), dtype=like.dtype))
    else:
        out[:3, :3] = rotation_y(np.asarray(float(angle), dtype=like.dtype))
    return out
