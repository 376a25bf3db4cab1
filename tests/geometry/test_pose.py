import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cylsfm.geometry import (
    axis_angle_to_matrix,
    compose,
    invert,
    mat_to_pose_vec,
    mat_to_tum,
    matrix_to_axis_angle,
    pose_vec_to_mat,
    quaternion_to_matrix,
    relative_pose,
    tum_to_mat,
    yaw_matrix,
)


def _random_vecs(seed: int, n: int = 16, max_angle: float = 3.1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    t = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 3
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    angle = torch.rand(n, 1, generator=gen, dtype=torch.float64) * max_angle
    return torch.cat((t, axis * angle), -1)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_pose_vector_round_trip(seed):
    vec = _random_vecs(seed)
    mat = pose_vec_to_mat(vec)
    rot = mat[:, :3, :3]
    assert torch.allclose(
        rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(16, 3, 3), atol=1e-12
    )
    assert torch.allclose(torch.linalg.det(rot), torch.ones(16, dtype=torch.float64))
    assert torch.allclose(mat_to_pose_vec(mat), vec, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_quaternion_round_trip_and_tum(seed):
    mat = pose_vec_to_mat(_random_vecs(seed, max_angle=math.pi))
    tum = mat_to_tum(mat)
    assert torch.allclose(tum[:, 3:].norm(dim=-1), torch.ones(16, dtype=torch.float64))
    assert (tum[:, 6] >= 0).all()
    assert torch.allclose(tum_to_mat(tum), mat, atol=1e-10)


def test_axis_angle_by_hand():
    # 90 degrees about z turns x into y
    rot = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert torch.allclose(
        rot @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 1, 0], dtype=torch.float64)
    )
    # quaternion of 90 degrees about z: (0, 0, sin 45, cos 45)
    q = torch.tensor([0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)], dtype=torch.float64)
    assert torch.allclose(quaternion_to_matrix(q), rot)
    # the angle pi round-trips (up to the sign of the axis, which is the same rotation)
    w = torch.tensor([0.0, math.pi, 0.0], dtype=torch.float64)
    back = matrix_to_axis_angle(axis_angle_to_matrix(w))
    assert torch.allclose(axis_angle_to_matrix(back), axis_angle_to_matrix(w), atol=1e-12)
    assert back.norm().item() == pytest.approx(math.pi)


def test_axis_angle_gradient_at_zero_is_finite():
    w = torch.zeros(3, requires_grad=True)
    axis_angle_to_matrix(w).sum().backward()
    assert torch.isfinite(w.grad).all()
    assert torch.allclose(w.grad, torch.zeros(3))  # d/dw of sum(I + [w]x) is zero at w = 0


def test_compose_invert_relative():
    a, b = pose_vec_to_mat(_random_vecs(1, 4)), pose_vec_to_mat(_random_vecs(2, 4))
    eye = torch.eye(4, dtype=torch.float64).expand(4, 4, 4)
    assert torch.allclose(compose(a, invert(a)), eye, atol=1e-12)
    assert torch.allclose(invert(compose(a, b)), compose(invert(b), invert(a)), atol=1e-12)
    rel = relative_pose(a, b)  # target a, source b
    p_tgt = torch.tensor([1.0, 2.0, 3.0, 1.0], dtype=torch.float64).view(4, 1)
    # the same world point expressed in both cameras
    world = a @ p_tgt
    assert torch.allclose(rel @ p_tgt, invert(b) @ world, atol=1e-12)


def test_yaw_matrix_increases_azimuth():
    r = yaw_matrix(torch.tensor(0.3, dtype=torch.float64), dtype=torch.float64)
    fwd = r @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    assert math.atan2(fwd[0].item(), fwd[2].item()) == pytest.approx(0.3)
    assert torch.allclose(matrix_to_axis_angle(r), torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64))


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="6 components"):
        pose_vec_to_mat(torch.zeros(2, 7))
    with pytest.raises(ValueError, match="7 values"):
        tum_to_mat(torch.zeros(2, 6))
