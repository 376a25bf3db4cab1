"""The convolutions on weights laid out once (inference on the CPU) against the plain ones."""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from cylsfm.model.build import build_models
from cylsfm.model.config import preset
from cylsfm.nn import DispNet, WrapConv2d, WrapConvTranspose2d, packed
from cylsfm.nn.packed import PackedWeights, plain_convolutions
from cylsfm.nn.padding import standard_ops

pytestmark = pytest.mark.skipif(
    not packed.available(torch.float32), reason="oneDNN's weight-layout ops are not in this torch"
)

DTYPES = [torch.float32] + ([torch.bfloat16] if packed.available(torch.bfloat16) else [])


def _tol(dtype: torch.dtype) -> dict:
    return {"rtol": 1e-4, "atol": 1e-4} if dtype == torch.float32 else {"rtol": 2e-2, "atol": 2e-2}


def _layers(wrap: bool) -> list[torch.nn.Module]:
    return [
        WrapConv2d(6, 5, 3, stride=1, wrap=wrap),
        WrapConv2d(6, 5, 5, stride=2, wrap=wrap),
        WrapConvTranspose2d(6, 5, 3, stride=2, wrap=wrap),
    ]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("wrap", [True, False])
@pytest.mark.parametrize("channels_last", [True, False])
@pytest.mark.parametrize("shape", [(2, 6, 1, 4), (1, 6, 2, 8), (3, 6, 9, 16)])
def test_layers_match_the_plain_convolutions(dtype, wrap, channels_last, shape):
    torch.manual_seed(0)
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    x = torch.randn(shape).to(dtype).contiguous(memory_format=fmt)
    for layer in _layers(wrap):
        layer = layer.to(dtype)
        with torch.no_grad():
            with plain_convolutions():
                plain = layer(x)
            fast = layer(x)
        assert len(layer.packed_weights) == 1, layer
        assert fast.shape == plain.shape and fast.dtype == plain.dtype
        assert fast.is_contiguous(memory_format=fmt) == plain.is_contiguous(memory_format=fmt)
        torch.testing.assert_close(fast, plain, **_tol(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_networks_match_the_plain_convolutions(dtype):
    torch.manual_seed(1)
    disp_net, pose_model = build_models(preset("default"))
    disp_net, pose_model = disp_net.eval().to(dtype), pose_model.eval().to(dtype)
    image = torch.rand(2, 3, 64, 256).contiguous(memory_format=torch.channels_last)
    sources = torch.rand(2, 2, 3, 64, 256)
    with torch.no_grad():
        with plain_convolutions():
            plain_disp = disp_net(image)
            plain_pose = pose_model.net(image.to(dtype), sources.to(dtype))[0]
        fast_disp = disp_net(image)
        fast_pose = pose_model.net(image.to(dtype), sources.to(dtype))[0]
    for a, b in zip(fast_disp, plain_disp, strict=True):
        torch.testing.assert_close(a.float(), b.float(), **_tol(dtype))
    torch.testing.assert_close(fast_pose.float(), plain_pose.float(), **_tol(dtype))
    used = [m for m in disp_net.modules() if isinstance(m, (WrapConv2d, WrapConvTranspose2d))]
    assert all(len(m.packed_weights) == 1 for m in used)


def test_a_changed_weight_is_laid_out_again():
    torch.manual_seed(2)
    net = DispNet(wrap=True).eval()
    other = DispNet(wrap=True).eval()
    x = torch.rand(1, 3, 64, 128)
    with torch.no_grad():
        before = net(x)[0]
        net.load_state_dict(other.state_dict())  # written in place: the version counters move
        after = net(x)[0]
        with plain_convolutions():
            expected = other(x)[0]
        net.encoder[0][0][0].weight.mul_(2.0)  # one weight written in place
        with plain_convolutions():
            expected_doubled = net(x)[0]
        doubled = net(x)[0]
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, expected, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(doubled, expected_doubled, rtol=1e-4, atol=1e-5)


def test_training_tracing_and_autocast_take_the_plain_path():
    layer = WrapConv2d(4, 4, 3)
    x = torch.randn(1, 4, 8, 16)
    layer(x).sum().backward()  # gradients recorded
    with torch.no_grad(), standard_ops():  # an exporter tracing
        layer(x)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):  # fp32 weights under autocast
        y = layer(x)
    assert y.dtype == torch.bfloat16
    with torch.inference_mode():  # weights made there keep no version counter
        made_inside = WrapConv2d(4, 4, 3)
        made_inside(x)
    assert len(layer.packed_weights) == 0 and len(made_inside.packed_weights) == 0
    with torch.no_grad():
        layer(x)
    assert len(layer.packed_weights) == 1


def test_copies_and_pickles_start_empty():
    import pickle

    net = DispNet(wrap=True).eval()
    x = torch.rand(1, 3, 64, 128)
    with torch.no_grad():
        y = net(x)[0]
    copied = copy.deepcopy(net)  # oneDNN's laid-out tensors cannot be copied: the copy starts empty
    assert len(copied.encoder[0][0][0].packed_weights) == 0
    with torch.no_grad():
        torch.testing.assert_close(copied(x)[0], y)
    again = pickle.loads(pickle.dumps(PackedWeights()))
    assert len(again) == 0


def test_shapes_remembered_are_bounded():
    layer = WrapConv2d(3, 3, 3).eval()
    with torch.no_grad():
        for width in range(8, 8 + 2 * (packed.MAX_SHAPES + 2), 2):
            x = torch.randn(1, 3, 4, width)
            expected = F.conv2d(
                torch.cat((x[..., -1:], x, x[..., :1]), -1), layer.weight, layer.bias, 1, (1, 0)
            )
            torch.testing.assert_close(layer(x), expected, rtol=1e-4, atol=1e-5)
    assert len(layer.packed_weights) == packed.MAX_SHAPES
