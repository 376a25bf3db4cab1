"""A ride's depth maps fused across neighbouring frames by their poses (cylsfm.geometry.fusion)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera
from cylsfm.geometry.fusion import fuse_depth


def _ride(frames=7, w=64, h=16):
    """A camera driving forward through a cylinder of radius 6 around its start (the ring's wall) with
    the exact cylindrical depth of every frame: ``(depths [M,1,H,W], c2w [M,4,4], camera)``."""
    cam = CylindricalCamera.full(w, h)
    c2w = torch.eye(4, dtype=torch.float64).repeat(frames, 1, 1)
    c2w[:, 2, 3] = 0.3 * torch.arange(frames)
    rays = cam.rays(cam.pixel_grid(1, dtype=torch.float64))[0]  # [3,H,W], unit horizontal length
    depths = []
    for j in range(frames):
        z0 = float(c2w[j, 2, 3])
        # |(0, z0) + d (x, z)| = 6 along the ray's horizontal direction (x, z) of unit length
        b = z0 * rays[2]
        d = -b + torch.sqrt(b**2 - (z0**2 - 36.0))
        depths.append(d[None])
    return torch.stack(depths).float(), c2w, cam


def test_depths_that_agree_are_kept_with_no_spread():
    depths, c2w, cam = _ride()
    fused, spread = fuse_depth(depths, c2w, cam, neighbours=3)
    inner = fused[1:-1]
    assert float((inner > 0).float().mean()) > 0.9  # points near the top and bottom leave the sources
    assert (inner[..., 2:-2, :] > 0).all()
    rel = ((inner - depths[1:-1]).abs() / depths[1:-1])[inner > 0]
    assert float(rel.max()) < 0.02 and float(spread[1:-1][inner > 0].median()) < 0.005


def test_an_error_of_one_frame_is_outvoted_by_its_neighbours():
    depths, c2w, cam = _ride()
    wrong = depths.clone()
    wrong[3, :, :, :32] *= 1.3  # the middle frame is 30% too far over half its panorama
    fused, spread = fuse_depth(wrong, c2w, cam, neighbours=3)
    before = float(((wrong[3] - depths[3]).abs() / depths[3]).mean())
    after = float(((fused[3] - depths[3]).abs() / depths[3]).mean())
    assert before > 0.14 and after < 0.3 * before
    # the six neighbours agree: the spread (around the median, robust) stays small
    assert float(spread[3, :, 2:-2].median()) < 0.03
    # its neighbours hardly move: one of seven frames is outvoted in theirs too
    assert float(((fused[2] - depths[2]).abs() / depths[2]).mean()) < 0.03


def test_a_ride_fused_in_chunks_gives_the_same_result():
    depths, c2w, cam = _ride(frames=9)
    depths[4, :, :, :20] *= 1.2
    whole = fuse_depth(depths, c2w, cam, neighbours=3)
    for chunk in (1, 2, 4):
        parts = fuse_depth(depths, c2w, cam, neighbours=3, chunk=chunk)
        for a, b in zip(whole, parts, strict=True):
            torch.testing.assert_close(a, b)


def test_pixels_seen_by_too_few_frames_or_unknown_have_no_fused_depth():
    depths, c2w, cam = _ride(frames=2)
    depths[0, :, :, :8] = 0  # unknown
    fused, spread = fuse_depth(depths, c2w, cam, neighbours=3, min_views=3)
    assert not fused.any() and not spread.any()  # two frames: never three views
    fused, _ = fuse_depth(depths, c2w, cam, neighbours=1, min_views=2)
    assert not fused[0, :, :, :8].any() and (fused[0, :, :, 8:] > 0).any()


def test_bad_shapes_are_named():
    depths, c2w, cam = _ride(frames=3)
    with pytest.raises(CylsfmError, match="c2w"):
        fuse_depth(depths, c2w[:2], cam)
    with pytest.raises(CylsfmError, match="camera"):
        fuse_depth(depths, c2w, CylindricalCamera.full(32, 8))
    with pytest.raises(CylsfmError, match="neighbours"):
        fuse_depth(depths, c2w, cam, neighbours=0)
    assert np.isfinite(fuse_depth(depths, c2w, cam)[0].numpy()).all()
