"""Direct alignment recovers known poses from true depth (the test of the refinement itself), across the
seam of a full panorama and on a pinhole view; the projection's Jacobian and the ground fit."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.errors import InputError, ShapeError
from cylsfm.geometry import (
    CylindricalCamera,
    EquirectangularCamera,
    PinholeCamera,
    projection_jacobian,
    relative_pose,
    roll_columns,
    rotation_y,
    yaw_matrix,
)
from cylsfm.geometry.ground import steady_height_steps
from cylsfm.geometry.photometric import photometric_inliers
from cylsfm.odometry import AlignConfig, align, ground_height, metric_scale


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    r = a[..., :3, :3].transpose(-1, -2) @ b[..., :3, :3]
    return torch.rad2deg(torch.arccos(((r.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))


def _pair(camera, target_c2w, source_c2w):
    tgt, depth = render_room(camera, target_c2w, supersample=2)
    src, _ = render_room(camera, source_c2w, supersample=2)
    true = relative_pose(target_c2w[None], source_c2w[None])[0]
    return tgt, src, depth, true


@pytest.mark.parametrize(
    ("camera", "rot_tol", "dir_tol"),
    # a 90-degree view confuses a small yaw with a sideways step far more than the full turn does: the
    # minimum of its photometric error lies a few tenths of a degree off (the rendering's aliasing decides
    # where along that valley); the panorama's lies within a few hundredths
    [(CylindricalCamera.full(160, 40), 0.1, 2.0), (PinholeCamera.from_fov(96, 64, 90.0), 0.5, 4.0)],
    ids=["panorama", "pinhole"],
)
def test_true_depth_recovers_the_pose_from_a_step_forward_guess(camera, rot_tol, dir_tol):
    # the target looks across the seam (yaw 180 degrees: the seam is straight ahead on the panorama)
    target = make_pose(0.0, 0.0, 0.0, yaw_deg=180.0 if camera.wraps else 10.0)
    source = make_pose(
        0.25, 0.05, -0.35 if camera.wraps else 0.35, yaw_deg=(180.0 if camera.wraps else 10.0) + 4.0
    )
    tgt, src, depth, true = _pair(camera, target, source)
    guess = torch.eye(4, dtype=torch.float64)[None].clone()
    guess[0, 2, 3] = -0.3  # "one usual step forward", no turn
    res = align(tgt, src, depth, guess, camera, config=AlignConfig(levels=3, iterations=10))
    assert _angle_deg(res.poses, true[None]).item() < rot_tol
    t, t_true = res.poses[0, :3, 3], true[:3, 3].double()
    assert torch.rad2deg(torch.arccos(torch.dot(t, t_true) / (t.norm() * t_true.norm()))).item() < dir_tol
    assert abs(t.norm() / t_true.norm() - 1) < 0.05
    assert res.cost.item() < res.start_cost.item()
    start_err = _angle_deg(guess, true[None]).item()
    assert start_err > 3.5  # it had something to do


def test_the_seam_is_crossed():
    """With wrapping every column is compared, also those whose points move across the seam."""
    cam = CylindricalCamera.full(160, 40)
    tgt, src, depth, true = _pair(
        cam, make_pose(0, 0, 0, yaw_deg=180.0), make_pose(0.1, 0, -0.3, yaw_deg=184.0)
    )
    guess = torch.eye(4, dtype=torch.float64)[None]
    wrapped = align(tgt, src, depth, guess, cam)
    cut = align(tgt, src, depth, guess, cam, wrap=False)
    assert _angle_deg(wrapped.poses, true[None]).item() < 0.1
    assert wrapped.valid.item() > cut.valid.item()  # the columns that cross the seam


def test_the_compass_candidate_is_taken_when_the_first_start_is_far_off():
    cam = CylindricalCamera.full(160, 40)
    tgt, src, depth, true = _pair(cam, make_pose(0, 0, 0, yaw_deg=30.0), make_pose(0.1, 0, 0.2, yaw_deg=70.0))
    wrong = torch.eye(4, dtype=torch.float64)  # no turn: 40 degrees off
    near = torch.eye(4, dtype=torch.float64)
    near[:3, :3] = yaw_matrix(math.radians(-40.0), dtype=torch.float64)  # the turn, no translation
    res = align(tgt, src, depth, torch.stack((wrong, near))[None], cam)
    assert res.start.item() == 1
    assert _angle_deg(res.poses, true[None]).item() < 0.2


def test_a_batch_aligns_each_pair_on_its_own():
    cam = CylindricalCamera.full(128, 32)
    pairs = [
        _pair(cam, make_pose(0, 0, 0, yaw_deg=y), make_pose(0.2, 0, 0.3, yaw_deg=y + d))
        for y, d in ((0.0, 2.0), (90.0, -3.0))
    ]
    tgt, src, depth = (torch.cat([p[i] for p in pairs]) for i in range(3))
    true = torch.stack([p[3] for p in pairs])
    res = align(tgt, src, depth, torch.eye(4, dtype=torch.float64).repeat(2, 1, 1), cam)
    assert (_angle_deg(res.poses, true) < 0.15).all()


def test_a_rolled_panorama_is_a_pure_yaw():
    cam = CylindricalCamera.full(128, 32)
    tgt, depth = render_room(cam, make_pose(0, 0, 0), supersample=2)
    src = roll_columns(tgt, 5)  # the camera turned by 5 columns, across the seam
    res = align(tgt, src, depth, torch.eye(4, dtype=torch.float64)[None], cam)
    yaw = math.degrees(math.atan2(res.poses[0, 0, 2].item(), res.poses[0, 0, 0].item()))
    assert yaw == pytest.approx(5 * 360 / 128, abs=0.05)
    assert res.poses[0, :3, 3].norm().item() < 0.02


def test_shapes_are_checked():
    cam = CylindricalCamera.full(32, 8)
    img = torch.rand(1, 3, 8, 32)
    with pytest.raises(ShapeError):
        align(img, img, torch.ones(1, 1, 8, 16), torch.eye(4)[None], cam)
    with pytest.raises(ShapeError):
        align(img, img, torch.ones(1, 1, 8, 32), torch.eye(4)[None], CylindricalCamera.full(64, 16))


@pytest.mark.parametrize(
    "camera",
    [
        CylindricalCamera.full(64, 16),
        PinholeCamera.from_fov(40, 30, 70.0),
        EquirectangularCamera.full(64, 32),
    ],
    ids=["cylindrical", "pinhole", "equirectangular"],
)
def test_projection_jacobian_matches_autograd(camera):
    torch.manual_seed(0)
    points = torch.randn(2, 3, 4, 5, dtype=torch.float64)
    points[:, 2] = points[:, 2].abs() + 0.5  # in front, for the pinhole
    jac = projection_jacobian(camera, points)
    for i in range(2):
        p = points.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(camera.project(p)[:, i].sum(), p)
        torch.testing.assert_close(jac[:, i], g)


def test_ground_height_of_the_room_floor():
    cam = CylindricalCamera.full(128, 32)
    _, depth = render_room(cam, make_pose(0.5, 0.3, -1.0), supersample=1)
    # the floor is at y = 1.6 (y points down), the camera at y = 0.3
    assert ground_height(depth, cam).item() == pytest.approx(1.3, rel=0.01)
    scale, used = metric_scale(ground_height(depth * 2.0, cam).numpy(), 1.3)
    assert scale == pytest.approx(0.5, rel=0.01) and used == 1


def test_steady_height_undoes_a_depth_unit_that_wanders_from_frame_to_frame():
    rng = np.random.default_rng(0)
    m = 12
    true = np.tile(np.eye(4), (m - 1, 1, 1))
    true[:, :3, :3] = rotation_y(rng.uniform(-0.1, 0.1, m - 1))
    true[:, :3, 3] = rng.normal(size=(m - 1, 3))
    unit = rng.uniform(0.7, 1.4, m)  # each frame's depth (and so each step) in its own unit
    steps = true.copy()
    steps[:, :3, 3] *= ((unit[:-1] + unit[1:]) / 2)[:, None]
    heights = 1.6 * unit  # the ground fitted in each frame, in that frame's unit
    heights[4] = np.nan  # no ground fit: the median's unit
    out, used = steady_height_steps(steps, heights)
    assert used == m - 1
    ok = [i for i in range(m - 1) if i not in (3, 4)]
    median = np.median(unit[np.isfinite(heights)])
    np.testing.assert_allclose(out[ok, :3, 3], true[ok, :3, 3] * median, rtol=1e-12)
    np.testing.assert_array_equal(out[:, :3, :3], steps[:, :3, :3])
    with pytest.raises(InputError, match="no frame shows a level ground"):
        steady_height_steps(steps, np.full(m, np.nan))
    with pytest.raises(InputError, match="heights"):
        steady_height_steps(steps, heights[:-1])


def test_inliers_insensitive_to_sampling_accept_a_long_baseline_and_still_reject_a_wrong_pose():
    camera = CylindricalCamera.full(160, 40)
    target = make_pose(0.0, 0.0, 0.0, yaw_deg=0.0)
    source = make_pose(0.9, 0.0, -0.6, yaw_deg=150.0)  # far across the room, turned round
    tgt, src, depth, true = _pair(camera, target, source)
    wrong = true.clone()[None]
    wrong[0, :3, :3] = (
        yaw_matrix(torch.tensor([math.radians(20.0)]), dtype=torch.float64)[0] @ wrong[0, :3, :3]
    )
    poses = torch.cat((true[None], wrong)).double()
    pair = (tgt.expand(2, -1, -1, -1), src.expand(2, -1, -1, -1), depth.expand(2, -1, -1, -1))
    plain = photometric_inliers(*pair, poses, camera, spread=0)
    insensitive = photometric_inliers(*pair, poses, camera)  # within a pixel (after Birchfield and Tomasi)
    assert (insensitive >= plain).all()  # the source's range always holds its bilinear sample
    assert (
        insensitive[0] > 0.9 > plain[0]
    )  # the right pose: nearly all texture explained once sampling is not
    assert insensitive[1] < 0.6  # a wrong pose (20 degrees off) stays below the loops' threshold
    same = photometric_inliers(tgt, tgt, depth, torch.eye(4, dtype=torch.float64)[None], camera, spread=0)
    assert same.item() == 1.0
    with pytest.raises(InputError, match="spread"):
        photometric_inliers(tgt, src, depth, true[None].double(), camera, spread=-1)


def test_picking_among_starts_costs_only_residuals_and_gives_what_linearising_each_would():
    """The alignment picks the cheapest of its starts from their residuals alone and linearises only the
    pose picked: the same pose, cost, residuals and Jacobian as linearising every start."""
    from cylsfm.geometry import align as align_module
    from cylsfm.geometry import photometric

    cam = CylindricalCamera.full(64, 16)
    tgt, src, depth, true = _pair(cam, make_pose(0.0, 0.1, 0.0), make_pose(0.1, 0.1, 0.3, yaw_deg=10.0))
    level = photometric.pyramid(tgt, src, depth, cam, True, 1)[0]
    starts = [torch.eye(4, dtype=torch.float64)[None], true[None].double(), (true @ true)[None].double()]
    pose, index, cost, res, jac, k = align_module._pick(level, starts)
    every = [photometric.residuals(level, p) for p in starts]
    k_all = photometric.robust_scale(every[0][0])
    costs = torch.stack([photometric.robust_cost(x[0], k_all) for x in every])
    assert (
        int(index) == int(costs.argmin(0)) == 1
        and torch.equal(k, k_all)
        and torch.equal(cost, costs.min(0).values)
    )
    assert torch.equal(pose, starts[1])
    want, points, sampled = every[1]
    for got, expected in zip((res.r, res.valid, res.usable), (want.r, want.valid, want.usable), strict=True):
        assert torch.equal(got, expected)
    assert torch.equal(jac, photometric.jacobian(cam, points, sampled))


@pytest.mark.parametrize("kwargs", [{"levels": 0}, {"iterations": -1}, {"huber": 0.0}, {"damping": -1.0}])
def test_settings_out_of_range_are_refused(kwargs):
    from cylsfm.geometry.align import AlignConfig

    with pytest.raises(InputError, match="must be"):
        AlignConfig(**kwargs)


@pytest.mark.parametrize("camera", [CylindricalCamera.full(64, 16), PinholeCamera.from_fov(64, 16, 90.0)])
def test_the_jacobian_is_the_image_gradient_through_the_projection(camera):
    """The residuals' Jacobian (formed in place for the cylinder) is ``grad I . dproject/dP . [I | -[P]x]``
    written out with the projection's own derivative."""
    from cylsfm.geometry import photometric, projection_jacobian

    g = torch.Generator().manual_seed(0)
    points = torch.randn(2, 3, 16, 64, generator=g) + torch.tensor([0.0, 0.0, 3.0]).reshape(1, 3, 1, 1)
    sampled = torch.randn(2, 3, 16, 64, generator=g)
    jp = projection_jacobian(camera, points)
    grad = sampled[:, 1:2] * jp[:, 0] + sampled[:, 2:3] * jp[:, 1]
    want = torch.cat((grad, torch.linalg.cross(points, grad, dim=1)), 1)
    got = photometric.jacobian(camera, points, sampled)
    assert got.shape == (2, 6, 16, 64)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4 * float(want.abs().max()))
