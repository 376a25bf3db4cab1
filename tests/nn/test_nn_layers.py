"""Tests for the wrap-around layers in cylsfm.nn.layers."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from cylsfm.nn import WrapConv2d, WrapConvTranspose2d, crop_like, set_wrap, wrap_upsample2x


def _circ_pad_w(x: torch.Tensor, p: int) -> torch.Tensor:
    """Reference circular padding of the width axis, written independently with index arithmetic."""
    w = x.shape[-1]
    idx = torch.arange(-p, w + p) % w
    return x[..., idx]


@pytest.mark.parametrize(
    ("k", "stride", "width"),
    [
        (1, 1, 16),
        (3, 1, 16),
        (3, 2, 16),
        (5, 2, 16),
        (7, 2, 32),
        (7, 1, 5),
        (3, 2, 9),
        (5, 1, 3),
        (3, 2, 2),
        (5, 1, 1),
        (7, 2, 2),
    ],
)
def test_wrap_conv2d_matches_circular_reference(k: int, stride: int, width: int) -> None:
    torch.manual_seed(0)
    conv = WrapConv2d(4, 6, k, stride=stride, wrap=True)
    x = torch.randn(2, 4, 11, width)
    p = (k - 1) // 2
    ref_in = F.pad(_circ_pad_w(x, p), (0, 0, p, p))  # circular horizontally, zeros vertically
    ref = F.conv2d(ref_in, conv.weight, conv.bias, stride=stride)
    out = conv(x)
    assert out.shape == ref.shape
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("k", "stride"), [(1, 1), (3, 1), (3, 2), (5, 2), (7, 2)])
def test_wrap_conv2d_off_equals_conv2d(k: int, stride: int) -> None:
    torch.manual_seed(1)
    conv = WrapConv2d(3, 5, k, stride=stride, wrap=False)
    ref = nn.Conv2d(3, 5, k, stride=stride, padding=(k - 1) // 2)
    ref.load_state_dict(conv.state_dict())
    x = torch.randn(2, 3, 13, 20)
    torch.testing.assert_close(conv(x), ref(x), atol=1e-6, rtol=1e-6)


def test_wrap_conv2d_wrap_changes_only_edge_columns_and_is_switchable() -> None:
    torch.manual_seed(2)
    conv = WrapConv2d(2, 3, 5, wrap=True)
    x = torch.randn(1, 2, 8, 24)
    wrapped = conv(x)
    conv.wrap = False
    plain = conv(x)
    # Interior columns (further than p=2 from either edge) are unaffected by the horizontal padding.
    torch.testing.assert_close(wrapped[..., 2:-2], plain[..., 2:-2])
    assert (wrapped[..., :2] - plain[..., :2]).abs().max() > 1e-3
    assert (wrapped[..., -2:] - plain[..., -2:]).abs().max() > 1e-3


@pytest.mark.parametrize(("k", "stride"), [(3, 1), (3, 2), (5, 2)])
def test_wrap_conv2d_roll_equivariance(k: int, stride: int) -> None:
    torch.manual_seed(3)
    conv = WrapConv2d(3, 4, k, stride=stride)
    x = torch.randn(1, 3, 7, 16)
    shift = 2 * stride
    torch.testing.assert_close(
        conv(torch.roll(x, shift, dims=-1)), torch.roll(conv(x), shift // stride, dims=-1), atol=1e-5, rtol=0
    )


@pytest.mark.parametrize("wrap", [True, False])
def test_wrap_conv2d_preserves_channels_last(wrap: bool) -> None:
    conv = WrapConv2d(8, 16, 3, stride=2, wrap=wrap)
    x = torch.randn(2, 8, 10, 16).contiguous(memory_format=torch.channels_last)
    out = conv(x)
    assert out.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(out, conv(x.contiguous()), atol=1e-5, rtol=1e-5)


def _tiled_conv_transpose_reference(x: torch.Tensor, layer: WrapConvTranspose2d) -> torch.Tensor:
    """Brute force: transposed conv of the 5x horizontally tiled input, keep the middle fifth."""
    s = layer.stride[1]
    w = x.shape[-1]
    full = F.conv_transpose2d(
        torch.cat([x] * 5, dim=-1),
        layer.weight,
        layer.bias,
        layer.stride,
        padding=layer.padding,
        output_padding=layer.output_padding,
    )
    return full[..., 2 * s * w : 3 * s * w]


@pytest.mark.parametrize(
    ("k", "stride", "width"), [(3, 2, 8), (3, 2, 1), (3, 2, 2), (5, 2, 7), (4, 2, 6), (5, 3, 5), (3, 1, 6)]
)
def test_wrap_conv_transpose_matches_tiled_reference(k: int, stride: int, width: int) -> None:
    torch.manual_seed(4)
    layer = WrapConvTranspose2d(4, 3, k, stride=stride, wrap=True)
    x = torch.randn(2, 4, 5, width)
    out = layer(x)
    assert out.shape == (2, 3, 5 * stride, width * stride)
    torch.testing.assert_close(out, _tiled_conv_transpose_reference(x, layer), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("k", "stride", "width"), [(3, 2, 8), (3, 2, 1), (3, 2, 2), (5, 2, 6), (5, 3, 4)])
def test_wrap_conv_transpose_is_adjoint_of_circular_conv(k: int, stride: int, width: int) -> None:
    """<convT_circ(x), y> == <x, conv_circ(y)> with the same weight, for the exact circular pair."""
    torch.manual_seed(5)
    layer = WrapConvTranspose2d(3, 2, k, stride=stride, bias=False, wrap=True)
    conv = WrapConv2d(2, 3, k, stride=stride, bias=False, wrap=True)
    with torch.no_grad():
        conv.weight.copy_(layer.weight)  # conv weight [3, 2, k, k] maps 2 -> 3 channels
    x = torch.randn(2, 3, 4, width, dtype=torch.float64)
    layer, conv = layer.double(), conv.double()
    y = torch.randn(2, 2, 4 * stride, width * stride, dtype=torch.float64)
    cy = conv(y)
    assert cy.shape == x.shape
    lhs = (layer(x) * y).sum()
    rhs = (x * cy).sum()
    torch.testing.assert_close(lhs, rhs, atol=1e-9, rtol=1e-9)


def test_wrap_conv_transpose_sfmlearner_shape_and_off_equals_conv_transpose() -> None:
    torch.manual_seed(6)
    layer = WrapConvTranspose2d(4, 5, wrap=False)
    ref = nn.ConvTranspose2d(4, 5, 3, stride=2, padding=1, output_padding=1)
    ref.load_state_dict(layer.state_dict())
    x = torch.randn(2, 4, 7, 9)
    out = layer(x)
    assert out.shape == (2, 5, 14, 18)
    torch.testing.assert_close(out, ref(x), atol=1e-6, rtol=1e-6)
    layer.wrap = True
    wrapped = layer(x)
    assert wrapped.shape == (2, 5, 14, 18)
    torch.testing.assert_close(wrapped[..., 2:-2], out[..., 2:-2], atol=1e-6, rtol=1e-6)
    assert (wrapped - out).abs().max() > 1e-3


def test_wrap_conv_transpose_roll_equivariance_and_channels_last() -> None:
    torch.manual_seed(7)
    layer = WrapConvTranspose2d(3, 4)
    x = torch.randn(1, 3, 5, 8)
    torch.testing.assert_close(
        layer(torch.roll(x, 3, dims=-1)), torch.roll(layer(x), 6, dims=-1), atol=1e-5, rtol=0
    )
    out_cl = layer(x.contiguous(memory_format=torch.channels_last))
    assert out_cl.stride(1) == 1  # channels stay innermost (the output is a column window, a view)
    torch.testing.assert_close(out_cl, layer(x), atol=1e-5, rtol=1e-5)


def test_wrap_conv_transpose_rejects_impossible_kernel_stride() -> None:
    with pytest.raises(ValueError, match="output_padding"):
        WrapConvTranspose2d(1, 1, kernel_size=2, stride=1)


def test_wrap_upsample2x() -> None:
    torch.manual_seed(8)
    x = torch.randn(2, 1, 4, 6)
    plain = wrap_upsample2x(x, wrap=False)
    torch.testing.assert_close(plain, F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False))
    up = wrap_upsample2x(x, wrap=True)
    assert up.shape == (2, 1, 8, 12)
    # Reference: interpolate the 3x tiled signal and keep the middle third (no edge clamping there).
    tiled = F.interpolate(torch.cat([x, x, x], -1), scale_factor=2, mode="bilinear", align_corners=False)
    torch.testing.assert_close(up, tiled[..., 12:24])
    # Column 0 blends the first and last input columns (weights 0.75 / 0.25 horizontally).
    row_up = wrap_upsample2x(torch.tensor([[[[1.0, 0.0, 0.0, 5.0]]]]), wrap=True)
    torch.testing.assert_close(row_up[0, 0, 0], torch.tensor([2.0, 0.75, 0.25, 0.0, 0.0, 1.25, 3.75, 4.0]))
    torch.testing.assert_close(wrap_upsample2x(torch.roll(x, 1, -1), True), torch.roll(up, 2, -1))


def test_crop_like() -> None:
    x = torch.arange(2 * 3 * 5 * 7.0).view(2, 3, 5, 7)
    ref = torch.zeros(1, 1, 4, 6)
    out = crop_like(x, ref)
    assert out.shape == (2, 3, 4, 6)
    torch.testing.assert_close(out, x[:, :, :4, :6])
    with pytest.raises(ValueError):
        crop_like(ref, x)


def test_set_wrap_flips_layers() -> None:
    model = nn.Sequential(WrapConv2d(1, 2, 3), nn.ReLU(), nn.Sequential(WrapConvTranspose2d(2, 1)))
    set_wrap(model, False)
    assert not model[0].wrap and not model[2][0].wrap
    set_wrap(model, True)
    assert model[0].wrap and model[2][0].wrap


def test_conv_transpose_forward_padded_equals_forward() -> None:
    torch.manual_seed(0)
    up = WrapConvTranspose2d(4, 3)
    x = torch.randn(2, 4, 5, 8)
    for pad in (1, 2):
        xp = torch.cat([x[..., -pad:], x, x[..., :pad]], -1)
        out, start = up.forward_padded(xp, pad)
        torch.testing.assert_close(out[..., start : start + 16], up(x))
    with pytest.raises(ValueError, match="padding"):
        up.forward_padded(x, 0)
