"""Colouring depth maps by inverse depth, and stacking previews."""

import matplotlib
import numpy as np
import pytest

from cylsfm.errors import CylsfmError
from cylsfm.export.colorize import colorize_depth, side_by_side


def _lightness(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def test_shape_dtype_and_unknown_pixels_are_black():
    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 50, size=(16, 40)).astype(np.float32)
    depth[0, :5] = 0
    depth[1, 0] = np.nan
    depth[1, 1] = np.inf
    depth[1, 2] = -3
    out = colorize_depth(depth)
    assert out.shape == (16, 40, 3) and out.dtype == np.uint8
    assert (out[0, :5] == 0).all() and (out[1, :3] == 0).all()
    assert (out[2:].max(axis=-1) > 0).all()  # magma's darkest colour is not pure black
    assert (colorize_depth(np.zeros((4, 6), np.float32)) == 0).all()


def test_near_is_bright_and_monotonic():
    depth = np.tile(np.linspace(1.0, 80.0, 200, dtype=np.float32), (3, 1))
    light = _lightness(colorize_depth(depth))[1]
    assert np.all(np.diff(light) <= 1e-9)
    assert light[0] > light[-1] + 150
    # other sequential colour maps read the same way
    light = _lightness(colorize_depth(depth, cmap="viridis"))[1]
    assert light[0] > light[-1]


def test_robust_percentiles_and_fixed_limits():
    depth = np.full((10, 100), 10.0, dtype=np.float32)
    depth[:, :50] = 5.0
    depth[0, 0] = 0.01  # one absurdly near pixel does not wash out the rest
    out = colorize_depth(depth)
    assert np.abs(_lightness(out[5, 10]) - _lightness(out[5, 80])) > 100
    np.testing.assert_array_equal(out[0, 0], out[5, 10])  # clipped to the brightest colour
    # fixed limits: depth <= vmin brightest, >= vmax darkest
    top = colorize_depth(np.array([[1.0, 2.0, 20.0, 100.0]], np.float32), vmin=2.0, vmax=20.0)
    np.testing.assert_array_equal(top[0, 0], top[0, 1])
    np.testing.assert_array_equal(top[0, 2], top[0, 3])
    assert _lightness(top[0, 0]) > _lightness(top[0, 2])
    with pytest.raises(ValueError, match="vmin"):
        colorize_depth(depth, vmin=0.0)


def test_fixed_limits_give_the_same_colours_in_every_frame():
    """Two frames of different depth ranges share depths 4, 8 and 12 m: with fixed limits each depth has one
    colour, that of its inverse depth's place between 1 / vmax and 1 / vmin; without limits it has not."""
    near = np.tile(np.linspace(1.5, 12.0, 64, dtype=np.float32), (4, 1))
    far = np.tile(np.linspace(4.0, 60.0, 64, dtype=np.float32), (4, 1))
    near[0, :3] = far[0, :3] = (4.0, 8.0, 12.0)
    vmin, vmax = 2.0, 20.0
    a, b = colorize_depth(near, vmin, vmax), colorize_depth(far, vmin, vmax)
    np.testing.assert_array_equal(a[0, :3], b[0, :3])
    lut = np.round(matplotlib.colormaps["magma"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    for frame, out in ((near, a), (far, b)):
        t = np.clip((1 / frame - 1 / vmax) / (1 / vmin - 1 / vmax), 0, 1)
        np.testing.assert_array_equal(out, lut[np.round(t * 255).astype(int)])
    # the negative: each frame stretched over its own percentiles colours the same depths differently
    auto_a, auto_b = colorize_depth(near), colorize_depth(far)
    assert all((auto_a[0, i] != auto_b[0, i]).any() for i in range(3))
    # only one limit fixed: the other end still follows the frame
    assert (colorize_depth(near, vmin=vmin)[0, :3] != colorize_depth(far, vmin=vmin)[0, :3]).any()


def test_constant_depth_and_bad_input():
    out = colorize_depth(np.full((3, 4), 7.0, np.float32))
    assert (out == out[0, 0]).all() and out[0, 0].max() > 0
    with pytest.raises(ValueError, match=r"\[H,W\]"):
        colorize_depth(np.ones((2, 3, 4), np.float32))
    with pytest.raises(CylsfmError, match="colour map"):
        colorize_depth(np.ones((2, 3), np.float32), cmap="no-such-map")


def test_side_by_side_stacks_vertically_with_a_separator():
    a = np.full((4, 10, 3), 10, np.uint8)
    b = np.full((6, 10), 20, np.uint8)  # grey is expanded to RGB
    out = side_by_side([a, b], separator=2)
    assert out.shape == (12, 10, 3) and out.dtype == np.uint8
    assert (out[:4] == 10).all() and (out[4:6] == 255).all() and (out[6:] == 20).all()
    assert side_by_side([a]).shape == a.shape
    with pytest.raises(ValueError, match="width"):
        side_by_side([a, np.zeros((4, 11, 3), np.uint8)])
    with pytest.raises(ValueError, match="uint8"):
        side_by_side([a.astype(np.float32)])


def _bar_rows(picture: np.ndarray, cmap: str = "magma") -> np.ndarray:
    """The rows of ``picture`` that are the colour scale: the colour map from its dark to its bright end
    across the width (tick marks aside)."""
    w = picture.shape[1]
    lut = np.round(matplotlib.colormaps[cmap](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    ramp = lut[np.linspace(0, 255, w).round().astype(int)]
    return np.flatnonzero((picture == ramp[None]).all(axis=2).mean(axis=1) > 0.95)


def test_depth_panels_readable_size_labels_and_a_colour_scale():
    """A 256x64 frame, its prediction and its ground truth: enlarged four times to 1024 pixels wide (the
    depth by repeating pixels, so each panel is exactly the colourised depth), each under its title, one
    colour scale for both depth maps, labelled in the unit."""
    from cylsfm.export.colorize import depth_panels, depth_picture

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (64, 256, 3), dtype=np.uint8)
    gt = np.tile(np.linspace(2.0, 40.0, 64, dtype=np.float32)[:, None], (1, 256))
    gt[:8] = 0  # the sky: no depth
    pred = gt * 1.1 + 0.5
    labels = ["input", "predicted depth", "ground truth"]
    pic = depth_panels(image, [pred, gt], "metres", labels=labels, limits=(2.0, 40.0))
    assert pic.dtype == np.uint8 and pic.shape[1] == 1024
    caption, sep = 16, 2
    top = caption + sep + 256 + sep + caption + sep  # the prediction's panel starts here
    np.testing.assert_array_equal(pic[top : top + 256 : 4, ::4], colorize_depth(pred, 2.0, 40.0))
    top += 256 + sep + caption + sep  # the ground truth's
    np.testing.assert_array_equal(pic[top : top + 256 : 4, ::4], colorize_depth(gt, 2.0, 40.0))
    assert (pic[top : top + 32] == 0).all()  # its sky stays black (unknown)
    bar = _bar_rows(pic)
    assert len(bar) >= 10 and bar.min() > top + 256  # the colour scale, below the pictures
    assert (pic[:caption].max(axis=2) > 150).any()  # a title's text
    # without titles the panels follow each other directly; one depth map: the input above it
    assert depth_panels(image, [pred, gt], limits=(2.0, 40.0)).shape[0] == pic.shape[0] - 3 * (caption + sep)
    single = depth_picture(image, gt)
    assert single.shape[1] == 1024 and len(_bar_rows(single)) >= 10
    with pytest.raises(ValueError, match="labels"):
        depth_panels(image, [pred, gt], labels=["only one"])
