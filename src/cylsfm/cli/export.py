"""``cylsfm export onnx``: the depth network as an ONNX model, checked against PyTorch."""

from __future__ import annotations

import argparse

from .base import command


def _export_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True, metavar="{onnx}")
    onnx = sub.add_parser(
        "onnx",
        help="the depth network as ONNX (image [B,3,H,W] in [0,1] -> depth [B,1,H,W]), wrap padding in "
        "standard operators",
    )
    onnx.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    onnx.add_argument("--out", required=True, help="the .onnx file to write")
    onnx.add_argument("--opset", type=int, default=18, help="ONNX operator set (default 18)")
    onnx.add_argument("--no-check", action="store_true", help="do not compare with PyTorch in ONNX Runtime")


@command("export", "export a trained model for other inference engines (ONNX)", _export_args)
def run_export(args: argparse.Namespace) -> int:
    from ..export.onnx import export_depth_onnx

    result = export_depth_onnx(args.checkpoint, args.out, opset=args.opset, check=not args.no_check)
    w, h = result.size
    print(f"wrote {result.path}: image [B,3,{h},{w}] in [0, 1] -> depth [B,1,{h},{w}] (network units)")
    if not args.no_check:
        print(
            f"ONNX Runtime against PyTorch on two test panoramas: max |difference| {result.max_abs_diff:.3g} "
            f"(relative {result.max_rel_diff:.3g})"
        )
    return 0
