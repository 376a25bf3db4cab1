"""Pose inference as odometry runs it: ``Predictor.ride_poses`` on the windows of three frames (a target and
its two neighbours) of consecutive frames, batches of 8 windows (10 frames; code without it: ``Predictor.poses``
on the 8 windows), with one pass and with the default further passes, in fp32 and with the
networks in bf16 (where the CPU has it natively). The networks are untrained (the work does not depend on
the weights); what bf16 does to the trained networks' accuracy is measured in RESULTS.md. With ``--before DIR`` the same measurements of the code
checked out in ``DIR`` (e.g. ``git worktree add DIR COMMIT``) run alternately with today's, so that both
are measured in one run on one machine state. Every measurement is its own process.

    python benchmarks/bench_pose_inference.py                               # 512x128
    python benchmarks/bench_pose_inference.py --before /tmp/before --reps 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path


def worker(size: tuple[int, int], iterations: int, amp: bool, reps: int, windows: int) -> dict:
    import inspect

    import torch

    from cylsfm.geometry import CylindricalCamera
    from cylsfm.model import Predictor, build_models, preset
    from cylsfm.model.build import LoadedModels

    w, h = size
    cfg = preset("default")
    cfg.data.width, cfg.data.height = w, h
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    models = LoadedModels(disp.eval(), pose.eval(), cfg, 0, Path("untrained"))
    kwargs = {"amp": amp} if "amp" in inspect.signature(Predictor).parameters else {}
    if amp and not kwargs:
        return {"skipped": "this code has no amp"}
    predictor = Predictor(models, "cpu", iterations, **kwargs)
    g = torch.Generator().manual_seed(0)
    coarse = torch.rand(windows + 2, 3, h // 8, w // 8, generator=g)
    frames = torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=False)
    cam = CylindricalCamera.full(w, h)
    tgt = frames[1:-1]
    src = torch.stack((frames[:-2], frames[2:]), 1)

    def run() -> torch.Tensor:
        if hasattr(predictor, "ride_poses"):  # as odometry reads them: each pair of frames once
            return torch.cat([predictor.ride_poses(frames[i : i + 10], cam) for i in range(0, windows, 8)])
        return torch.cat([predictor.poses(tgt[i : i + 8], src[i : i + 8], cam) for i in range(0, windows, 8)])

    out = run()  # warm-up
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    networks = "bf16" if getattr(predictor, "dtype", None) == torch.bfloat16 else "fp32"
    return {
        "ms_per_window": 1e3 * statistics.median(times) / windows,
        "networks": networks,
        "poses": out.tolist(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="512x128", help="WxH")
    ap.add_argument("--windows", type=int, default=32)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--before", help="a checkout of the earlier code to measure beside today's")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if args.worker:
        print(json.dumps(worker(size, *json.loads(args.worker), args.reps, args.windows)))
        return
    here = Path(__file__).resolve().parents[1]
    codes = [("before", Path(args.before).resolve())] if args.before else []
    codes.append(("today", here))
    results = {}
    for iterations in (0, 3):
        for amp in (False, True):
            for name, code in codes:
                env = {**os.environ, "PYTHONPATH": str(code / "src")}
                cmd = [sys.executable, __file__, "--size", args.size, "--windows", str(args.windows)]
                cmd += ["--reps", str(args.reps), "--worker", json.dumps([iterations, amp])]
                out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
                results[(name, iterations, amp)] = json.loads(out.strip().splitlines()[-1])
    import torch

    print(f"{args.size}, batches of 8 windows, {torch.get_num_threads()} threads, median of {args.reps}")
    print("| code | further passes | networks | ms per window | / before, fp32 |")
    print("|---|---|---|---|---|")
    for (name, iterations, amp), r in results.items():
        if "skipped" in r or (amp and r["networks"] == "fp32"):  # no native bf16 here: the fp32 row again
            continue
        ref = results.get(("before", iterations, False)) or results[("today", iterations, False)]
        ratio = r["ms_per_window"] / ref["ms_per_window"]
        print(f"| {name} | {iterations} | {r['networks']} | {r['ms_per_window']:.1f} | {ratio:.2f}x |")
    if args.before:
        for iterations in (0, 3):
            a = torch.tensor(results[("before", iterations, False)]["poses"], dtype=torch.float64)
            b = torch.tensor(results[("today", iterations, False)]["poses"], dtype=torch.float64)
            print(
                f"fp32, {iterations} passes: today's poses against before's: max |difference| {float((a - b).abs().max()):.2g}"
            )


if __name__ == "__main__":
    main()
