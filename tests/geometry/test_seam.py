"""The seam of full panoramas (cylsfm.geometry.seam, and the networks' fused padding kernels of
cylsfm.nn.padding): circular padding (plain and fused), differences,
wrapped resizes and the yaw rolls of panoramas and their poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cylsfm.geometry import (
    CylindricalCamera,
    circular_pad,
    column_difference,
    inverse_warp,
    pad_for_window,
    relative_pose,
    resize_image,
    roll_angle,
    roll_columns,
    roll_pose,
    rotation_x,
    rotation_y,
    rotation_z,
    yaw_matrix,
)
from cylsfm.geometry.seam import memory_format_of
from cylsfm.nn import padding
from cylsfm.nn.padding import pad_cat, relu_pad


def _reference_pad(x: torch.Tensor, left: int, right: int) -> torch.Tensor:
    """Circular padding of the width written independently, with index arithmetic."""
    w = x.shape[-1]
    return x[..., torch.arange(-left, w + right) % w]


@pytest.mark.parametrize(("left", "right", "width"), [(0, 0, 5), (1, 1, 5), (2, 1, 5), (3, 0, 2), (7, 9, 3)])
@pytest.mark.parametrize("pad", [circular_pad, padding.circular_pad], ids=["geometry", "nn"])
def test_circular_pad_matches_index_arithmetic_with_gradients(left: int, right: int, width: int, pad) -> None:
    torch.manual_seed(0)
    x = torch.randn(2, 3, 4, width, requires_grad=True)
    out, ref = pad(x, left, right), _reference_pad(x, left, right)
    torch.testing.assert_close(out, ref, rtol=0, atol=0)
    g = torch.randn_like(ref)
    (got,) = torch.autograd.grad((out * g).sum(), x)
    (want,) = torch.autograd.grad((ref * g).sum(), x)
    torch.testing.assert_close(got, want)


def test_zero_padding_of_the_fused_kernels_is_a_bounded_image() -> None:
    y = torch.randn(1, 2, 3, 5)
    torch.testing.assert_close(relu_pad(y, 2, circular=False), torch.nn.functional.pad(y.relu(), (2, 2)))
    a, b = torch.randn(1, 1, 3, 5), torch.randn(1, 2, 3, 5)
    want = torch.nn.functional.pad(torch.cat((a, b), 1), (1, 1))
    torch.testing.assert_close(pad_cat([a, b], 1, circular=False), want)


def test_pad_for_window_is_circular_across_and_reflected_along() -> None:
    x = torch.arange(12.0).reshape(1, 1, 3, 4)
    out = pad_for_window(x, wrap=True)
    assert out.shape == (1, 1, 5, 6)
    torch.testing.assert_close(out[..., 1:-1, :], _reference_pad(x, 1, 1))
    torch.testing.assert_close(out[..., 0, :], out[..., 2, :])  # reflection: row -1 is row 1
    plain = pad_for_window(x, wrap=False)
    torch.testing.assert_close(plain[..., 1:-1, 0], x[..., :, 1])  # reflected, not wrapped


def test_column_difference_crosses_the_seam_only_with_wrap() -> None:
    x = torch.tensor([[[[1.0, 4.0, 9.0, 16.0]]]])
    torch.testing.assert_close(column_difference(x, True), torch.tensor([[[[3.0, 5.0, 7.0, -15.0]]]]))
    torch.testing.assert_close(column_difference(x, False), torch.tensor([[[[3.0, 5.0, 7.0]]]]))


def test_wrapped_resize_is_periodic_bilinear_interpolation() -> None:
    torch.manual_seed(0)
    x = torch.randn(1, 2, 3, 8)
    out = resize_image(x, (6, 16), wrap=True)
    # roll-equivariance: rolling the input by one column rolls the output by two
    torch.testing.assert_close(resize_image(torch.roll(x, 1, -1), (6, 16), True), torch.roll(out, 2, -1))
    # the first output column lies a quarter pixel left of column 0: 3/4 of column 0, 1/4 of column 7
    cols = torch.nn.functional.interpolate(x, size=(6, 8), mode="bilinear", align_corners=False)
    torch.testing.assert_close(out[..., 0], 0.75 * cols[..., 0] + 0.25 * cols[..., 7])
    with pytest.raises(ValueError, match="integer width factor"):
        resize_image(x, (6, 12), wrap=True)


def test_roll_columns_on_tensors_and_arrays() -> None:
    t = torch.arange(6).reshape(1, 6)
    assert roll_columns(t, 0) is t
    assert roll_columns(t, 2).tolist() == [[4, 5, 0, 1, 2, 3]]
    a = np.arange(12).reshape(2, 6, 1)  # [H, W, C] frames roll along axis 1
    assert roll_columns(a, -1, axis=1)[:, :, 0].tolist() == [[1, 2, 3, 4, 5, 0], [7, 8, 9, 10, 11, 6]]
    assert math.isclose(roll_angle(3, 12), math.pi / 2)


def test_rolled_panoramas_with_rolled_poses_warp_alike() -> None:
    """Roll target and source panoramas (and the target depth) by k columns and turn the relative pose
    with roll_pose: the warped image is the rolled warp of the original; the wrong sign is not."""
    cam = CylindricalCamera.full(64, 16)
    torch.manual_seed(0)
    src = torch.rand(1, 3, 16, 64)
    depth = 2.0 + torch.rand(1, 1, 16, 64)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = yaw_matrix(0.2, torch.float64) @ torch.from_numpy(rotation_x(np.asarray(0.05)))
    pose[:3, 3] = torch.tensor([0.3, 0.0, 0.5], dtype=torch.float64)
    k = 16  # a quarter turn: exact on the pixel grid
    warped, _ = inverse_warp(src, depth, pose[None].float(), cam)
    rolled, _ = inverse_warp(
        roll_columns(src, k), roll_columns(depth, k), roll_pose(pose, k, 64)[None].float(), cam
    )
    torch.testing.assert_close(rolled, roll_columns(warped, k), atol=2e-4, rtol=0)
    wrong, _ = inverse_warp(
        roll_columns(src, k), roll_columns(depth, k), roll_pose(pose, -k, 64)[None].float(), cam
    )
    assert (wrong - roll_columns(warped, k)).abs().mean() > 0.05


def test_roll_pose_of_camera_to_world_poses_matches_relative_poses() -> None:
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[1, :3, :3] = rotation_y(np.asarray(0.3))
    c2w[1, :3, 3] = [1.0, 0.0, 2.0]
    k, w = 5, 40
    rolled = roll_pose(c2w, k, w, camera_to_world=True)
    rel = relative_pose(torch.from_numpy(c2w[0]), torch.from_numpy(c2w[1])).numpy()
    rel_rolled = relative_pose(torch.from_numpy(rolled[0]), torch.from_numpy(rolled[1])).numpy()
    np.testing.assert_allclose(rel_rolled, roll_pose(rel, k, w), atol=1e-12)


def test_numpy_and_torch_rotations_agree() -> None:
    a = np.linspace(-3, 3, 7)
    for rot in (rotation_x, rotation_y, rotation_z):
        np.testing.assert_allclose(rot(a), rot(torch.from_numpy(a)).numpy(), rtol=0, atol=1e-15)
        np.testing.assert_allclose(
            rot(a) @ np.swapaxes(rot(a), -1, -2), np.broadcast_to(np.eye(3), (7, 3, 3)), atol=1e-12
        )


def test_pad_cat_equals_cat_then_circular_pad_with_gradients() -> None:
    torch.manual_seed(0)
    a = torch.randn(2, 3, 4, 8, requires_grad=True)
    b = torch.randn(2, 5, 4, 8, requires_grad=True)
    for pad in (1, 2):
        out = pad_cat([a, b], pad)
        ref = torch.cat([a, b], 1)
        ref = torch.cat([ref[..., -pad:], ref, ref[..., :pad]], -1)
        torch.testing.assert_close(out, ref)
        g = torch.randn_like(ref)
        ga, gb = torch.autograd.grad((out * g).sum(), (a, b))
        ra, rb = torch.autograd.grad((ref * g).sum(), (a, b))
        torch.testing.assert_close(ga, ra)
        torch.testing.assert_close(gb, rb)
    cl = pad_cat([a.contiguous(memory_format=torch.channels_last), b], 1)
    assert cl.is_contiguous(memory_format=torch.channels_last)


def test_pad_cat_of_windows_and_memory_format() -> None:
    torch.manual_seed(0)
    # a feature kept padded by 2 columns (its centre is the window) and an up-convolution output
    padded = torch.randn(2, 4, 5, 12).contiguous(memory_format=torch.channels_last).requires_grad_(True)
    up = torch.randn(2, 3, 5, 8).contiguous(memory_format=torch.channels_last).requires_grad_(True)
    out = pad_cat([up, padded], 1, width=8, starts=[0, 2], memory_format=torch.channels_last)
    ref = torch.cat([up, padded[..., 2:10]], 1)
    ref = torch.cat([ref[..., -1:], ref, ref[..., :1]], -1)
    torch.testing.assert_close(out, ref)
    assert out.is_contiguous(memory_format=torch.channels_last)
    g = torch.randn_like(ref)
    got = torch.autograd.grad((out * g).sum(), (up, padded))
    want = torch.autograd.grad((ref * g).sum(), (up, padded))
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b)
    assert got[1][..., :2].abs().sum() == 0 and got[1][..., 10:].abs().sum() == 0
    with pytest.raises(ValueError, match="padding"):
        pad_cat([up], 9)


def testmemory_format_of_a_column_window() -> None:
    x = torch.randn(2, 4, 5, 12)
    assert memory_format_of(x) == torch.contiguous_format
    assert memory_format_of(x[..., 1:11]) == torch.contiguous_format
    cl = x.contiguous(memory_format=torch.channels_last)
    assert memory_format_of(cl) == torch.channels_last
    # a window is contiguous in neither format but laid out channels-last
    assert memory_format_of(cl[..., 1:11]) == torch.channels_last


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize(("pad", "window"), [(0, None), (2, None), (1, (4, 2, 8)), (3, (5, 0, 6)), (9, None)])
def test_relu_pad_equals_relu_then_pad(channels_last: bool, pad: int, window) -> None:
    torch.manual_seed(0)
    y = torch.randn(2, 3, 5, 8 if window is None else 11)
    if channels_last:
        y = y.contiguous(memory_format=torch.channels_last)
    y.requires_grad_(True)
    out = relu_pad(y, pad, window)
    h, s, w = window if window is not None else (5, 0, 8)
    ref = torch.relu(y[..., :h, s : s + w])
    ref = (
        torch.cat([ref] * 3, -1)[..., w - pad : 2 * w + pad]
        if pad <= w
        else torch.cat([ref] * 5, -1)[..., 2 * w - pad : 3 * w + pad]
    )
    torch.testing.assert_close(out, ref)
    if channels_last and pad <= w:
        assert out.is_contiguous(memory_format=torch.channels_last)
    g = torch.randn_like(ref)
    (got,) = torch.autograd.grad((out * g).sum(), y)
    (want,) = torch.autograd.grad((ref * g).sum(), y)
    torch.testing.assert_close(got, want)
