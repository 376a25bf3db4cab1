"""Time finding the direction of travel (``cylsfm.odometry.mount.mount_yaw``), the once-per-ride step of
``cylsfm odometry`` on full panoramas: 32 frames, 12 pairs aligned from 8 directions each.

    python benchmarks/bench_mount.py                  # 512x128, median of 3
    python benchmarks/bench_mount.py --size 256x64

The alignment does a fixed number of iterations, so random images with a constant depth take the time of
real ones.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from cylsfm.geometry import CylindricalCamera
from cylsfm.odometry.mount import mount_yaw


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="512x128")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    cam = CylindricalCamera.full(w, h)
    images = torch.rand(32, 3, h, w, generator=torch.Generator().manual_seed(0))
    depth = torch.full((32, 1, h, w), 5.0)
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        mount_yaw(images, depth, cam, step_length=0.1)
        times.append(time.perf_counter() - t)
    runs = ", ".join(f"{t:.2f}" for t in times)
    print(f"mount_yaw {w}x{h}: median {statistics.median(times):.2f} s ({runs})")


if __name__ == "__main__":
    main()
