"""The ONNX export of the depth network: standard operators only, the same depth as PyTorch."""

from __future__ import annotations

import pytest
import torch

from cylsfm.cli import main
from cylsfm.model import build_models, save_checkpoint
from cylsfm.model.config import apply_overrides, config_to_dict, preset
from cylsfm.nn import DispNet, PoseExpNet
from cylsfm.nn.padding import standard_ops

onnxruntime = pytest.importorskip("onnxruntime")


def _checkpoint(path, *overrides):
    """An untrained 256x64 model of the default recipe saved at ``path``; returns ``(path, config, DispNet)``."""
    cfg = apply_overrides(preset("default"), ["data.width=256", "data.height=64", *overrides])
    disp, pose = build_models(cfg)
    state = {
        "config": config_to_dict(cfg),
        "step": 0,
        "disp_net": disp.state_dict(),
        "pose_net": pose.state_dict(),
    }
    save_checkpoint(path, state)
    return path, cfg, disp


def test_standard_ops_give_the_same_networks_outputs():
    """The plain-operator padding (what the exporter traces) computes what the fused padding computes."""
    torch.manual_seed(0)
    disp, pose = DispNet().eval(), PoseExpNet(n_sources=2, explainability=True).eval()
    x = torch.rand(2, 3, 64, 256).contiguous(memory_format=torch.channels_last)
    src = torch.rand(2, 2, 3, 64, 256)
    with torch.no_grad():
        fused = disp(x), pose(x, src)
        with standard_ops():
            plain = disp(x), pose(x, src)
    for a, b in zip(fused[0], plain[0], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fused[1][0], plain[1][0], rtol=1e-5, atol=1e-7)


def test_export_onnx_matches_pytorch_and_wraps(tmp_path, capsys):
    torch.manual_seed(0)
    ckpt, _, disp = _checkpoint(tmp_path / "model.pt")
    out = tmp_path / "depth.onnx"
    assert main(["export", "onnx", "--checkpoint", str(ckpt), "--out", str(out)]) == 0
    assert "max |difference|" in capsys.readouterr().out
    session = onnxruntime.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    image = torch.rand(3, 3, 64, 256)  # another batch size than the export's
    (got,) = session.run(["depth"], {"image": image.numpy()})
    with torch.no_grad():
        want = 1.0 / disp.eval()(image)[0].clamp(min=1e-6)
    torch.testing.assert_close(torch.from_numpy(got), want, rtol=1e-4, atol=1e-4)
    # the wrap padding survived the export: rolling the panorama by the network's stride rolls the depth
    (rolled,) = session.run(["depth"], {"image": torch.roll(image, 128, -1).numpy()})
    torch.testing.assert_close(
        torch.from_numpy(rolled), torch.roll(torch.from_numpy(got), 128, -1), rtol=1e-4, atol=1e-4
    )


def test_export_of_a_missing_checkpoint_is_a_clear_error(tmp_path, capsys):
    assert (
        main(["export", "onnx", "--checkpoint", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "x.onnx")])
        == 2
    )
    assert "nope.pt" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()


def test_export_of_a_crop_trained_model_takes_the_crop(tmp_path):
    """A model trained on a 180-degree crop (no wrap-around) exports at the crop's width."""
    from cylsfm.export.onnx import export_depth_onnx

    ckpt, cfg, _ = _checkpoint(tmp_path / "crop.pt", "data.fov=180")
    assert not cfg.wrap
    result = export_depth_onnx(ckpt, tmp_path / "crop.onnx")
    assert result.size == (128, 64) and result.max_rel_diff < 1e-4
