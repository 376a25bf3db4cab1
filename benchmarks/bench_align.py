"""Time one direct alignment (``cylsfm.geometry.align.align``) as ``cylsfm odometry --refine`` calls it: a
batch of 8 pairs at 512x128, two starts each (the network's pose and the compass's yaw), 3 levels of 8
iterations. With ``--before DIR`` the code checked out in ``DIR`` (``git worktree add DIR COMMIT``) runs in
its own process, alternating with today's, and the results of both are compared.

    python benchmarks/bench_align.py
    python benchmarks/bench_align.py --before /tmp/before --rounds 2

The images are smooth random noise, the source the target turned by two columns, the depth smooth random
values between 2 and 10: the work per iteration does not depend on the content, but how many steps are
accepted does (a rejected step skips its Jacobian), so real rides may gain less or more.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_train_step import median_time  # the benchmarks' one timer (from this folder)


def worker(size: tuple[int, int], batch: int, reps: int, out: Path) -> dict:
    import torch
    import torch.nn.functional as F

    from cylsfm.geometry import CylindricalCamera
    from cylsfm.geometry.align import align

    torch.manual_seed(0)
    w, h = size
    cam = CylindricalCamera.full(w, h)
    target = F.avg_pool2d(torch.rand(batch, 3, h, w), 9, 1, 4).clamp(0, 1)
    depth = 2 + 8 * F.avg_pool2d(torch.rand(batch, 1, h, w), 15, 1, 7)
    source = torch.roll(target, 2, -1)
    init = torch.eye(4, dtype=torch.float64).repeat(batch, 2, 1, 1)
    init[:, 0, 2, 3] = 0.1
    result = align(target, source, depth, init, cam)
    seconds = median_time(
        lambda: align(target, source, depth, init, cam), reps, warmup=0
    )  # the call above warmed up
    torch.save({k: getattr(result, k) for k in ("poses", "cost", "start_cost", "start", "valid")}, out)
    return {"ms": 1e3 * seconds}


def _run(code: str | None, args: argparse.Namespace, out: Path) -> dict:
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = str(Path(code) / "src")
    cmd = [sys.executable, __file__, "--worker", str(out), "--size", args.size]
    cmd += ["--batch", str(args.batch), "--reps", str(args.reps)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="512x128", help="WxH")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=1, help="alternating rounds with --before")
    ap.add_argument("--before", help="a checkout of the earlier code to measure beside today's")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.worker:
        print(json.dumps(worker((w, h), args.batch, args.reps, Path(args.worker))))
        return
    import torch

    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads; align, {args.batch} pairs at {w}x{h}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        codes = [("today", None)] + ([("before", args.before)] if args.before else [])
        for n in range(args.rounds):
            for name, code in codes:
                got = _run(code, args, Path(tmp) / f"{name}.pt")
                print(f"round {n + 1}, {name}: {got['ms']:.1f} ms")
        if args.before:
            a, b = (torch.load(Path(tmp) / f"{name}.pt", weights_only=True) for name in ("today", "before"))
            diff = max(float((a[k].double() - b[k].double()).abs().max()) for k in a)
            print(f"largest difference of the results, today against before: {diff:.3g}")


if __name__ == "__main__":
    main()
