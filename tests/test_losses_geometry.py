"""The terms of a ride's own adjusted geometry: the sparse depth term, the pose term, and how the training
objective applies them (the mask, the poses that warp)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cylsfm.geometry import CylindricalCamera, pose_vec_to_mat
from cylsfm.losses import DENSE_FLOOR, LossConfig, dense_depth_term, sfm_pose_term, sparse_depth_term
from cylsfm.train.objective import Batch, Objective


def _points(b=2, h=8, w=32, n=20, seed=0):
    """A depth ``[B,1,H,W]`` and its sparse points ``[B,2,H,W]`` (``n`` a frame, sigma 0.05)."""
    gen = torch.Generator().manual_seed(seed)
    depth = 2.0 + 10.0 * torch.rand(b, 1, h, w, generator=gen)
    sparse = torch.zeros(b, 2, h, w)
    for i in range(b):
        at = torch.randperm(h * w, generator=gen)[:n]
        sparse[i, 0].view(-1)[at] = depth[i, 0].view(-1)[at]
        sparse[i, 1].view(-1)[at] = 0.05
    return depth, sparse


def test_sparse_term_is_zero_where_the_depth_explains_the_points_and_grows_with_an_error():
    depth, sparse = _points()
    assert float(sparse_depth_term(1.0 / depth, sparse)) < 1e-10
    losses = [float(sparse_depth_term(1.0 / (depth * (1 + e)), sparse)) for e in (0.01, 0.05, 0.2)]
    assert 0 < losses[0] < losses[1] < losses[2]
    off = depth.clone()
    off[sparse[:, :1] == 0] *= 3.0  # wrong where there is no point: no matter
    assert float(sparse_depth_term(1.0 / off, sparse)) < 1e-10
    assert float(sparse_depth_term(1.0 / depth, torch.zeros_like(sparse))) == 0.0  # no point: no term


def test_sparse_term_weighs_by_uncertainty_and_an_outlier_pulls_little():
    depth, sparse = _points(n=40)
    sure, unsure = sparse.clone(), sparse.clone()
    unsure[:, 1][unsure[:, 1] > 0] = 0.5
    wrong = 1.0 / (depth * 1.1)
    assert float(sparse_depth_term(wrong, unsure)) < 0.2 * float(sparse_depth_term(wrong, sure))
    far = depth.clone()
    first = torch.nonzero(sparse[0, 0] > 0)[0]
    far[0, 0, first[0], first[1]] *= 100.0  # one wrong match
    disp = (1.0 / far).requires_grad_()
    sparse_depth_term(disp, sure).backward()
    near = depth.clone()
    near[0, 0, first[0], first[1]] *= 1.05
    disp2 = (1.0 / near).requires_grad_()
    sparse_depth_term(disp2, sure).backward()
    at = (0, 0, int(first[0]), int(first[1]))
    # Cauchy: the far outlier's pull on its depth's logarithm is smaller than a 5% error's
    assert abs(float(disp.grad[at] * (1.0 / far)[at])) < abs(float(disp2.grad[at] * (1.0 / near)[at]))


def test_dense_term_is_zero_at_the_fused_depth_grows_with_an_error_and_trusts_no_spread_below_its_floor():
    gen = torch.Generator().manual_seed(3)
    depth = 2.0 + 10.0 * torch.rand(2, 1, 8, 32, generator=gen)
    dense = torch.cat((depth, torch.full_like(depth, 0.01)), 1)
    dense[:, :, :2] = 0  # rows without a fused depth
    assert float(dense_depth_term(1.0 / depth, dense)) < 1e-10
    losses = [float(dense_depth_term(1.0 / (depth * (1 + e)), dense)) for e in (0.01, 0.05, 0.2)]
    assert 0 < losses[0] < losses[1] < losses[2]
    off = depth.clone()
    off[:, :, :2] *= 3.0  # wrong where nothing was fused: no matter
    assert float(dense_depth_term(1.0 / off, dense)) < 1e-10
    # a spread below the floor counts as the floor: sigma = DENSE_FLOOR exactly
    r = 0.1
    want = float(torch.log1p(torch.tensor(r / DENSE_FLOOR) ** 2))
    assert float(dense_depth_term(1.0 / (depth * np.exp(r)), dense)) == pytest.approx(want, rel=1e-4)
    wide = dense.clone()
    wide[:, 1] = 0.5  # the frames disagree: the target pulls less
    assert float(dense_depth_term(1.0 / (depth * 1.2), wide)) < 0.2 * losses[2]
    assert float(dense_depth_term(1.0 / depth, torch.zeros_like(dense))) == 0.0


def test_pose_term_is_zero_for_the_adjusted_poses_and_grows_with_an_error():
    gen = torch.Generator().manual_seed(1)
    vec = torch.cat([torch.randn(2, 2, 3, generator=gen), 0.05 * torch.randn(2, 2, 3, generator=gen)], -1)
    sfm = pose_vec_to_mat(vec)
    valid = torch.full((2, 2), 0.3)  # the ride's median step
    assert float(sfm_pose_term(sfm, sfm, valid)) < 1e-6
    errors = []
    for e in (0.01, 0.05, 0.2):
        off = vec.clone()
        off[..., 0] += e
        off[..., 4] += e
        errors.append(float(sfm_pose_term(pose_vec_to_mat(off), sfm, valid)))
    assert 0 < errors[0] < errors[1] < errors[2]
    off = vec.clone()
    off[..., 0] += 0.03  # a tenth of a step
    assert float(sfm_pose_term(pose_vec_to_mat(off), sfm, valid)) == pytest.approx(0.1, rel=1e-4)
    off = vec.clone()
    off[0, 1, :3] += 5.0  # a pair without the ride's geometry: no matter
    valid[0, 1] = 0
    assert float(sfm_pose_term(pose_vec_to_mat(off), sfm, valid)) < 1e-6
    assert float(sfm_pose_term(sfm, sfm, torch.zeros(2, 2))) == 0.0


def _batch(sparse, mask=None, seed=0):
    gen = torch.Generator().manual_seed(seed)
    b, _, h, w = sparse.shape
    cam = CylindricalCamera.full(w, h)
    pose = pose_vec_to_mat(torch.tensor([[0.0, 0.0, 0.3, 0.0, 0.0, 0.0], [0.0, 0.0, -0.3, 0.0, 0.0, 0.0]]))
    sfm = (sparse, pose.expand(b, 2, 4, 4).clone(), torch.full((b, 2), 0.3))
    target = torch.rand(b, 3, h, w, generator=gen)
    return Batch(target, torch.rand(b, 2, 3, h, w, generator=gen), cam.stack([cam] * b), mask, sfm)


def _outputs(depth, vec):
    disps = [1.0 / depth] + [torch.nn.functional.avg_pool2d(1.0 / depth, 2**s) for s in (1, 2, 3)]
    return disps, vec, None, {}


def test_objective_adds_the_terms_and_ignores_points_under_the_mask():
    depth, sparse = _points(b=2, h=16, w=64)
    cfg = LossConfig(sfm_depth_weight=0.5, sfm_pose_weight=0.5)
    vec = torch.tensor([[0.0, 0.0, 0.3, 0.0, 0.0, 0.0], [0.0, 0.0, -0.3, 0.0, 0.0, 0.0]]).expand(2, 2, 6)
    _, terms, _ = Objective(cfg, wrap=True)(_batch(sparse), _outputs(depth, vec))
    assert float(terms["sfm_depth"]) < 1e-8 and float(terms["sfm_pose"]) < 1e-6
    wrong = depth.clone()
    wrong[:, :, :, :32] *= 1.5  # wrong on the left half
    _, terms, _ = Objective(cfg, wrap=True)(_batch(sparse), _outputs(wrong, vec))
    assert float(terms["sfm_depth"]) > 0.1
    mask = torch.ones(1, 1, 16, 64)
    mask[..., :32] = 0  # an occluder over the left half: its points are no target
    _, terms, _ = Objective(cfg, wrap=True)(_batch(sparse, mask), _outputs(wrong, vec))
    assert float(terms["sfm_depth"]) < 1e-8


def test_objective_adds_the_dense_term_from_the_targets_last_two_channels():
    depth, sparse = _points(b=2, h=16, w=64)
    dense = torch.cat((depth, torch.full_like(depth, 0.05)), 1)
    targets = torch.cat((sparse, dense), 1)  # [B,4,H,W] as the dataset gives them
    vec = torch.tensor([[0.0, 0.0, 0.3, 0.0, 0.0, 0.0], [0.0, 0.0, -0.3, 0.0, 0.0, 0.0]]).expand(2, 2, 6)
    cfg = LossConfig(sfm_depth_weight=0.5, sfm_dense_weight=2.0)
    _, terms, _ = Objective(cfg, wrap=True)(_batch(targets), _outputs(depth, vec))
    assert float(terms["sfm_dense"]) < 1e-8 and float(terms["sfm_depth"]) < 1e-8
    wrong = depth * 1.1
    _, terms, _ = Objective(cfg, wrap=True)(_batch(targets), _outputs(wrong, vec))
    want = 2.0 * float(dense_depth_term(1.0 / wrong, dense))
    assert float(terms["sfm_dense"]) == pytest.approx(want, rel=1e-5) and want > 0.1
    _, terms, _ = Objective(LossConfig(sfm_depth_weight=0.5), wrap=True)(
        _batch(targets), _outputs(wrong, vec)
    )
    assert "sfm_dense" not in terms


def test_synthesis_warps_with_the_adjusted_poses_where_the_ride_has_them(monkeypatch):
    import cylsfm.train.objective as objective

    seen = []
    real = objective.view_synthesis_loss

    def spy(target, sources, disps, poses, *args, **kwargs):
        seen.append(poses.clone())
        return real(target, sources, disps, poses, *args, **kwargs)

    monkeypatch.setattr(objective, "view_synthesis_loss", spy)
    depth, sparse = _points(b=2, h=16, w=64)
    still = torch.zeros(2, 2, 6)  # the network says: no motion
    batch = _batch(sparse)
    batch.sfm[2][1, 0] = 0  # the second sample's first source has no geometry
    Objective(LossConfig(), wrap=True)(batch, _outputs(depth, still))
    Objective(LossConfig(sfm_synthesis=True), wrap=True)(batch, _outputs(depth, still))
    eye = torch.eye(4).expand(2, 2, 4, 4)
    torch.testing.assert_close(seen[0], eye)  # the predicted poses
    want = batch.sfm[1].clone()
    want[1, 0] = torch.eye(4)  # the predicted pose where the ride has none
    torch.testing.assert_close(seen[1], want)
