"""Time ``cylsfm odometry`` on a long ride: frames per second with the pose network alone (one pass, and
the default further passes over its own warp) and with the refinement, and where the time goes.

The ride is rendered by ``cylsfm synth`` (one sequence, cached in the output folder) and the model is the
default recipe's networks at the ride's size, untrained: the work per frame does not depend on the weights.
Both runs use the same process, one after the other, so their ratio is measured on one machine state.

    python benchmarks/bench_odometry.py                              # 1000 frames at 512x128
    python benchmarks/bench_odometry.py --frames 200 --size 256x64   # a quick look
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import torch

import cylsfm
from cylsfm.data.synth import generate_dataset
from cylsfm.model import build_models, preset, save_checkpoint
from cylsfm.model.config import config_to_dict
from cylsfm.odometry import OdometrySettings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--size", default="512x128", help="WxH")
    ap.add_argument("--keyframes", type=int, default=1, help="--keyframes of the refined run")
    ap.add_argument("--work", default=None, help="folder for the ride (kept; default: a temporary one)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_odometry_"))
    data = work / f"ride_{w}x{h}_{args.frames}"
    if not (data / "seq_000" / "camera.json").is_file():
        generate_dataset(
            data, sequences=1, frames=args.frames, width=w, height=h, seed=0, progress=True, overwrite=True
        )
    cfg = preset("default")
    cfg.data.width, cfg.data.height = w, h
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    ckpt = work / "model.pt"
    save_checkpoint(
        ckpt,
        {
            "config": config_to_dict(cfg),
            "step": 0,
            "disp_net": disp.state_dict(),
            "pose_net": pose.state_dict(),
        },
    )
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {args.frames} frames at {w}x{h}")
    for name, opts in (
        ("pose network alone, one pass (--pose-iterations 0)", {"pose_iterations": 0}),
        ("pose network alone (default: 3 further passes)", {}),
        (f"--refine --keyframes {args.keyframes}", {"refine": True, "keyframe_every": args.keyframes}),
    ):
        out = work / "out"
        shutil.rmtree(out, ignore_errors=True)
        result = cylsfm.odometry(
            data / "seq_000", ckpt, out, OdometrySettings(device="cpu", progress=False, **opts)
        )
        n = len(result.c2w)
        parts = ", ".join(f"{k} {v:.1f} s" for k, v in sorted(result.timings.items(), key=lambda kv: -kv[1]))
        print(f"{name}: {result.seconds:.1f} s, {n / result.seconds:.2f} frames/s ({parts})")
        print(json.dumps({"run": name, "seconds": result.seconds, "frames": n, "timings": result.timings}))


if __name__ == "__main__":
    main()
