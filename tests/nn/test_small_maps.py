"""The matrix-product path for tiny feature maps computes what F.conv2d / F.conv_transpose2d compute."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from cylsfm.nn import DispNet, small_maps
from cylsfm.nn.small_maps import conv2d_rows_padded, conv_transpose2d_small


def _value_and_grads(fn, *tensors):
    for t in tensors:
        t.grad = None
    out = fn()
    out.backward(torch.linspace(-1, 1, out.numel()).reshape(out.shape))
    return [out.detach()] + [t.grad.clone() for t in tensors]


def _close(a, b):
    for x, y in zip(a, b, strict=True):
        assert x.shape == y.shape
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(
    ("shape", "stride", "kernel"),
    [
        ((2, 6, 1, 6), 1, 3),
        ((2, 6, 2, 10), 1, 3),
        ((2, 6, 2, 10), 2, 3),
        ((2, 6, 1, 8), 1, 5),
        ((2, 6, 3, 7), 2, 3),
    ],
)
@pytest.mark.parametrize("bias", [True, False])
def test_conv_matches_conv2d_values_and_gradients(shape, stride, kernel, bias):
    torch.manual_seed(0)
    pad = (kernel - 1) // 2
    x = torch.randn(shape, requires_grad=True)
    w = torch.randn(4, shape[1], kernel, kernel, requires_grad=True)
    b = torch.randn(4, requires_grad=True) if bias else None
    tensors = (x, w) + ((b,) if bias else ())
    ours = _value_and_grads(lambda: conv2d_rows_padded(x, w, b, stride, pad), *tensors)
    plain = _value_and_grads(lambda: F.conv2d(x, w, b, stride, (pad, 0)), *tensors)
    _close(ours, plain)


@pytest.mark.parametrize("shape", [(2, 6, 1, 4), (2, 6, 2, 6), (1, 3, 3, 5)])
def test_transposed_conv_matches_conv_transpose2d(shape):
    torch.manual_seed(1)
    x = torch.randn(shape, requires_grad=True)
    w = torch.randn(shape[1], 5, 3, 3, requires_grad=True)
    b = torch.randn(5, requires_grad=True)
    ours = _value_and_grads(lambda: conv_transpose2d_small(x, w, b, (2, 2), (1, 1), (1, 1)), x, w, b)
    plain = _value_and_grads(lambda: F.conv_transpose2d(x, w, b, 2, 1, 1), x, w, b)
    assert ours[0].shape == (shape[0], 5, 2 * shape[2], 2 * shape[3])
    _close(ours, plain)


def test_large_maps_and_inference_take_the_plain_path(monkeypatch):
    calls = []
    monkeypatch.setattr(small_maps.torch, "matmul", lambda *a: calls.append(1) or torch.Tensor.matmul(*a))
    w = torch.randn(4, 3, 3, 3, requires_grad=True)
    conv2d_rows_padded(torch.randn(1, 3, 8, 10), w, None, 1, 1)  # 64 positions: oneDNN
    with torch.no_grad():
        conv2d_rows_padded(torch.randn(1, 3, 2, 6), w, None, 1, 1)  # no gradients recorded: oneDNN
    assert calls == []
    conv2d_rows_padded(torch.randn(1, 3, 2, 6), w, None, 1, 1)
    assert calls == [1]


def test_network_gradients_do_not_depend_on_the_path(monkeypatch):
    torch.manual_seed(2)
    net = DispNet(wrap=True)
    x = torch.rand(2, 3, 64, 256)

    def grads():
        net.zero_grad()
        sum(d.mean() for d in net(x)).backward()
        return [p.grad.clone() for p in net.parameters()]

    fast = grads()
    monkeypatch.setattr(small_maps, "MAX_POSITIONS", 0)
    plain = grads()
    for a, b in zip(fast, plain, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-5)


def test_channels_last_inputs_give_channels_last_outputs():
    x = torch.randn(2, 6, 2, 10).contiguous(memory_format=torch.channels_last).requires_grad_()
    w = torch.randn(4, 6, 3, 3, requires_grad=True)
    y = conv2d_rows_padded(x, w, None, 1, 1)
    assert y.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(y, F.conv2d(x, w, None, 1, (1, 0)), rtol=1e-4, atol=1e-4)
    up = conv_transpose2d_small(x, torch.randn(6, 4, 3, 3), None, (2, 2), (1, 1), (1, 1))
    assert up.is_contiguous(memory_format=torch.channels_last)
