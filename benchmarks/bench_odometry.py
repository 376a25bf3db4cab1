"""Time ``cylsfm odometry`` on a long ride: frames per second with the pose network alone (one pass, and
the default further passes over its own warp) and with the refinement, and where the time goes.

The ride is rendered by ``cylsfm synth`` (one sequence, cached in the output folder) and the model is the
default recipe's networks at the ride's size, untrained: the work per frame does not depend on the weights.
The runs follow one another in one invocation, each in its own process, so their ratio is measured on
one machine state: fp32 and, where the CPU has native bf16, the networks in bf16 (``amp``); with
``--before DIR`` also the code checked out in ``DIR`` (e.g. ``git worktree add DIR COMMIT``), in fp32.

    python benchmarks/bench_odometry.py                              # 1000 frames at 512x128
    python benchmarks/bench_odometry.py --frames 200 --size 256x64   # a quick look
    python benchmarks/bench_odometry.py --frames 200 --before /tmp/before
    python benchmarks/bench_odometry.py --before /tmp/before --runs passes   # the further passes only
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

import cylsfm
from cylsfm.data.synth import generate_dataset
from cylsfm.odometry import OdometrySettings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--size", default="512x128", help="WxH")
    ap.add_argument("--keyframes", type=int, default=1, help="--keyframes of the refined run")
    ap.add_argument("--work", default=None, help="folder for the ride (kept; default: a temporary one)")
    ap.add_argument("--before", help="a checkout of the earlier code to measure beside today's (fp32)")
    ap.add_argument(
        "--runs",
        default="one-pass,passes,refine",
        help="which runs, comma-separated: one-pass, passes (the default 3 further passes), refine",
    )
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    from cylsfm.model import untrained_checkpoint  # today's; a worker may run an earlier code without it

    w, h = (int(v) for v in args.size.split("x"))
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_odometry_"))
    data = work / f"ride_{w}x{h}_{args.frames}"
    if not (data / "seq_000" / "camera.json").is_file():
        generate_dataset(
            data, sequences=1, frames=args.frames, width=w, height=h, seed=0, progress=True, overwrite=True
        )
    ckpt = untrained_checkpoint(work / "model.pt", w, h)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {args.frames} frames at {w}x{h}")
    here = Path(__file__).resolve().parents[1]
    codes = [("before", Path(args.before).resolve())] if args.before else []
    codes.append(("today", here))
    runs = {
        "one-pass": ("pose network alone, one pass (--pose-iterations 0)", {"pose_iterations": 0}),
        "passes": ("pose network alone (default: 3 further passes)", {}),
        "refine": (
            f"--refine --keyframes {args.keyframes}",
            {"refine": True, "keyframe_every": args.keyframes},
        ),
    }
    chosen = args.runs.split(",")
    if unknown := set(chosen) - set(runs):
        ap.error(f"--runs: unknown {sorted(unknown)}; choose from {sorted(runs)}")
    for name, opts in (runs[r] for r in chosen):
        for code_name, code in codes:
            for amp in (False, True) if code_name == "today" else (False,):
                job = json.dumps(
                    {"data": str(data / "seq_000"), "ckpt": str(ckpt), "work": str(work), "amp": amp, **opts}
                )
                env = {**os.environ, "PYTHONPATH": str(code / "src")}
                out = subprocess.run(
                    [sys.executable, __file__, "--worker", job],
                    env=env,
                    capture_output=True,
                    text=True,
                    check=True,
                ).stdout
                r = json.loads(out.strip().splitlines()[-1])
                if amp and r["networks"] == "fp32":
                    continue  # no native bf16 on this CPU: the same as the fp32 run
                parts = ", ".join(
                    f"{k} {v:.1f} s" for k, v in sorted(r["timings"].items(), key=lambda kv: -kv[1])
                )
                print(
                    f"{name} [{code_name}, {r['networks']}]: {r['seconds']:.1f} s, "
                    f"{r['frames'] / r['seconds']:.2f} frames/s ({parts})"
                )
                print(json.dumps({"run": name, "code": code_name, **r}))


def worker(job: dict) -> dict:
    """One odometry run of ``job`` with the ``cylsfm`` on ``PYTHONPATH``."""
    out = Path(job.pop("work")) / "out"
    shutil.rmtree(out, ignore_errors=True)
    data, ckpt, amp = job.pop("data"), job.pop("ckpt"), job.pop("amp")
    if amp and "amp" not in inspect.signature(OdometrySettings).parameters:
        return {"networks": "fp32", "seconds": 0.0, "frames": 0, "timings": {}}
    params = inspect.signature(OdometrySettings).parameters
    extra = {"amp": amp} if "amp" in params else {}
    if "bundle" in params:  # the refinement's speed: the bundle adjustment (on with refine) left out
        extra["bundle"] = False
    result = cylsfm.odometry(data, ckpt, out, OdometrySettings(device="cpu", progress=False, **extra, **job))
    from cylsfm.model import Predictor

    networks = (
        "bf16" if amp and getattr(Predictor.from_checkpoint(ckpt, "cpu", amp=True), "dtype", None) else "fp32"
    )
    return {
        "networks": networks,
        "seconds": result.seconds,
        "frames": len(result.c2w),
        "timings": result.timings,
    }


if __name__ == "__main__":
    main()
