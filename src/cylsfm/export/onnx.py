"""The depth network as an ONNX model, for ONNX Runtime and other inference engines.

The exported graph takes panoramas at the network's input size and returns depth (network units):

    image  float32 [B,3,H,W] in [0, 1]   ->   depth  float32 [B,1,H,W]  (1 / the finest disparity)

The wrap-around padding of every convolution is expressed in standard operators (slices and ``Concat``,
:func:`cylsfm.nn.padding.standard_ops`), so any ONNX runtime executes it; the batch size is dynamic.
:func:`export_depth_onnx` checks the exported model against PyTorch on the same input and reports the
largest difference.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from ..atomic import atomic_write_bytes
from ..errors import CylsfmError
from ..geometry import CylindricalCamera
from ..model import Predictor, load_models
from ..nn.padding import standard_ops

__all__ = ["DepthOutput", "OnnxExport", "export_depth_onnx", "export_onnx", "onnx_session"]


class DepthOutput(nn.Module):
    """DispNet's finest disparity turned into depth: ``[B,3,H,W] -> [B,1,H,W]`` (network units)."""

    def __init__(self, disp_net: nn.Module) -> None:
        super().__init__()
        self.disp_net = disp_net

    def forward(self, image: Tensor) -> Tensor:
        return 1.0 / self.disp_net(image)[0].clamp(min=1e-6)


@dataclass
class OnnxExport:
    """What :func:`export_depth_onnx` wrote and how closely it agrees with PyTorch."""

    path: Path
    size: tuple[int, int]  # (W, H) of the network's input
    max_abs_diff: float  # largest |depth_onnx - depth_torch| on the check input
    max_rel_diff: float  # largest |depth_onnx - depth_torch| / depth_torch


def onnx_session(path: str | os.PathLike[str], threads: int | None = None):
    """An ONNX Runtime CPU session for ``path`` (``threads``: intra-op threads, default ONNX Runtime's)."""
    try:
        import onnxruntime as ort
    except ImportError:
        raise CylsfmError("ONNX Runtime is not installed: pip install onnxruntime") from None
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def export_onnx(model: nn.Module, example: Tensor, out: str | os.PathLike[str], opset: int = 18) -> None:
    """Export ``model`` (one image input ``[B,3,H,W]`` -> ``depth``) to ``out`` with a dynamic batch size.

    The wrap padding is traced in standard operators (:func:`~cylsfm.nn.padding.standard_ops`); the file
    is written atomically (:mod:`cylsfm.atomic`), so a reader never sees half a model and a full disk
    keeps a previous one.
    """
    try:
        with standard_ops(), torch.no_grad(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=UserWarning)
            program = torch.onnx.export(
                model,
                (example,),
                dynamo=True,
                input_names=["image"],
                output_names=["depth"],
                dynamic_shapes=({0: torch.export.Dim("batch", min=1, max=4096)},),
                opset_version=opset,
            )
    except ImportError as exc:
        raise CylsfmError(f"ONNX export needs the onnx and onnxscript packages ({exc})") from None
    atomic_write_bytes(out, program.model_proto.SerializeToString())  # (the initializers included)


def export_depth_onnx(
    checkpoint: str | os.PathLike[str], out: str | os.PathLike[str], opset: int = 18, check: bool = True
) -> OnnxExport:
    """Export the depth network of ``checkpoint`` (a file or run directory) to ``out`` (written atomically).

    Args:
        checkpoint: a cylsfm checkpoint or run directory.
        out: the ``.onnx`` file to write.
        opset: the ONNX operator set.
        check: run the exported model with ONNX Runtime on a test panorama and compare with PyTorch.

    Raises:
        CylsfmError: the checkpoint cannot be read, or the ONNX packages are missing.
    """
    predictor = Predictor(load_models(checkpoint, "cpu"))
    width, height = predictor.network_camera(CylindricalCamera.full(*predictor.size)).size
    model = DepthOutput(predictor.models.disp_net.float()).eval()
    example = torch.rand(2, 3, height, width, generator=torch.Generator().manual_seed(0))
    export_onnx(model, example, out, opset)
    abs_diff = rel_diff = float("nan")
    if check:
        with torch.no_grad():
            want = model(example).numpy()
        got = onnx_session(out).run(["depth"], {"image": example.numpy()})[0]
        abs_diff = float(np.abs(got - want).max())
        rel_diff = float((np.abs(got - want) / np.abs(want)).max())
    return OnnxExport(Path(out), (width, height), abs_diff, rel_diff)
