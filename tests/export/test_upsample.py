"""Depth upsampled guided by the panorama's colours: depth edges move to the colour edges of the fine
image, the seam wraps, unknown depth stays unknown, and a smooth depth stays as it was."""

from __future__ import annotations

import numpy as np
import pytest

from cylsfm.errors import CylsfmError
from cylsfm.export.upsample import guided_upsample

W, H, S = 64, 16, 8  # coarse size and the factor to the fine one


def _step(edge: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A near wall (depth 2, light) left of fine column ``edge``, a far one (depth 8, dark) right of it: the
    coarse depth is the area average, so one coarse pixel mixes both."""
    fine = np.where((np.arange(W * S) - edge) % (W * S) < W * S // 2, 8.0, 2.0)
    guide = np.where(fine[None, :, None] == 2.0, 200, 30).astype(np.uint8).repeat(H * S, 0).repeat(3, 2)
    coarse = np.tile(fine.reshape(W, S).mean(1), (H, 1)).astype(np.float32)
    return coarse, guide, fine


@pytest.mark.parametrize("edge", [203, 5])  # the second edge is one coarse pixel from the seam
def test_depth_edges_follow_the_colour_edges(edge):
    coarse, guide, fine = _step(edge)
    up = guided_upsample(coarse, guide)
    assert up.shape == (H * S, W * S)
    assert np.abs(up - fine[None]).max() < 0.01  # exact to the fine pixel, across the seam too
    plain = np.repeat(coarse, S, 1)  # what the coarse pixels alone say
    assert np.abs(plain - fine[None]).max() > 1


def test_smooth_depth_and_unknown_depth():
    v, u = np.mgrid[0:H, 0:W]
    depth = (3 + np.sin(2 * np.pi * u / W) + 0.05 * v).astype(np.float32)
    guide = np.full((H * S, W * S, 3), 120, np.uint8)
    up = guided_upsample(depth, guide)
    x = (np.arange(W * S) + 0.5) / S - 0.5
    y = (np.arange(H * S) + 0.5) / S - 0.5
    truth = 3 + np.sin(2 * np.pi * x / W)[None] + 0.05 * np.clip(y, 0, H - 1)[:, None]
    assert np.abs(up - truth)[S:-S].max() < 0.02
    depth[:4] = 0  # an unknown sky
    up = guided_upsample(depth, guide)
    assert (up[: 4 * S - S // 2] == 0).all() and (up[4 * S + S // 2 :] > 0).all()


def test_a_guide_smaller_than_the_depth_is_refused():
    with pytest.raises(CylsfmError, match="guide"):
        guided_upsample(np.ones((16, 64), np.float32), np.zeros((8, 32, 3), np.uint8))
