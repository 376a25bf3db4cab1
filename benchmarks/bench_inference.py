"""One panorama's depth: the wrap-aware DispNet in PyTorch and in ONNX Runtime, against the same network in
SfMLearner's own configuration (pinhole: no wrap, fp32, contiguous memory, eager PyTorch), in one run.

    python benchmarks/bench_inference.py                    # 512x128, batch 1
    python benchmarks/bench_inference.py --size 256x64 --batch 8
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from bench_train_step import median_time  # the benchmarks' one timer (run from benchmarks/)


def _median_ms(fn, reps: int) -> float:
    return 1e3 * median_time(fn, reps, warmup=3)


def main(argv: list[str] | None = None) -> None:
    from cylsfm.export.onnx import DepthOutput, export_onnx, onnx_session
    from cylsfm.nn import DispNet
    from cylsfm.nn.packed import plain_convolutions
    from cylsfm.runtime import native_bf16

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--size", default="512x128")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--reps", type=int, default=30)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    reference = DepthOutput(DispNet(wrap=False)).eval()
    model = DepthOutput(DispNet(wrap=True)).eval()
    model.load_state_dict(reference.state_dict())
    x = torch.rand(args.batch, 3, h, w)
    x_cl = x.contiguous(memory_format=torch.channels_last)
    model_cl = DepthOutput(DispNet(wrap=True)).eval().to(memory_format=torch.channels_last)
    model_cl.load_state_dict(reference.state_dict())
    # as Predictor runs it where bf16 is native: a bf16 copy of the weights, fp32 images in and out
    model_bf16 = copy.deepcopy(model_cl).to(torch.bfloat16) if native_bf16() else None
    plain, packed = "plain convolutions", "weights laid out once"
    rows = []
    with torch.no_grad():
        with plain_convolutions():
            ref_ms = _median_ms(lambda: reference(x), args.reps)
            rows.append(("SfMLearner configuration: pinhole, fp32, contiguous, eager", ref_ms))
            rows.append((f"cylsfm, contiguous, {plain}", _median_ms(lambda: model(x), args.reps)))
            rows.append((f"cylsfm, channels_last, {plain}", _median_ms(lambda: model_cl(x_cl), args.reps)))
        ms = _median_ms(lambda: model_cl(x_cl), args.reps)
        rows.append((f"cylsfm, channels_last, {packed}" + ("" if model_bf16 else " (the default here)"), ms))
        if model_bf16 is not None:
            bf16 = "channels_last, bf16 network"
            with plain_convolutions():
                ms = _median_ms(lambda: model_bf16(x_cl).float(), args.reps)
            rows.append((f"cylsfm, {bf16}, {plain}", ms))
            rows.append(
                (
                    f"cylsfm, {bf16}, {packed} (the default here)",
                    _median_ms(lambda: model_bf16(x_cl).float(), args.reps),
                )
            )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "depth.onnx"
        export_onnx(model, x, path)
        session = onnx_session(path, threads=args.threads)
        feed = {"image": x.numpy()}
        rows.append(
            ("cylsfm, ONNX Runtime (CPU)", _median_ms(lambda: session.run(["depth"], feed), args.reps))
        )
        with torch.no_grad():
            diff = float(np.abs(session.run(["depth"], feed)[0] - model(x).numpy()).max())
    print(
        f"{w}x{h}, batch {args.batch}, {args.threads} threads, torch {torch.__version__}, median of {args.reps}"
    )
    print("| implementation | ms | ratio to the SfMLearner configuration |")
    print("|---|---|---|")
    for name, ms in rows:
        print(f"| {name} | {ms:.1f} | {ms / ref_ms:.2f}x |")
    print(f"ONNX Runtime against PyTorch: max |depth difference| {diff:.3g}")


if __name__ == "__main__":
    sys.exit(main())
