"""Frames per second of the synthetic street generator, end to end (render + write PNG and depth).

python benchmarks/bench_synth.py                       # the figures of BENCHMARKS.md
python benchmarks/bench_synth.py --size 256x64 --frames 60
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time

from cylsfm.data.synth import SynthConfig, generate_dataset


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--size", default="512x128", help="WxH (default 512x128)")
    parser.add_argument("--frames", type=int, default=120, help="frames per run (one sequence)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per configuration (median)")
    parser.add_argument("--workers", default=f"1,{os.cpu_count()}", help="comma-separated worker counts")
    parser.add_argument("--moving-objects", action="store_true")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    print(f"{args.frames} frames at {w}x{h}, median of {args.repeats} runs")
    print("| workers | anti-aliasing | frames/s | s/frame |")
    print("|---|---|---|---|")
    for aa in (1, 2):
        for workers in (int(v) for v in args.workers.split(",")):
            rates = []
            for r in range(args.repeats):
                out = tempfile.mkdtemp(prefix="cylsfm-bench-synth-")
                try:
                    t0 = time.perf_counter()
                    generate_dataset(
                        out,
                        sequences=1,
                        frames=args.frames,
                        width=w,
                        height=h,
                        seed=r,
                        moving_objects=args.moving_objects,
                        workers=workers,
                        config=SynthConfig(supersample=aa),
                        progress=False,
                    )
                    rates.append(args.frames / (time.perf_counter() - t0))
                finally:
                    shutil.rmtree(out, ignore_errors=True)
            fps = statistics.median(rates)
            name = "quincunx (2 rays/px)" if aa == 1 else f"{aa}x{aa} grid (+ centre)"
            print(f"| {workers} | {name} | {fps:.1f} | {1 / fps:.3f} |")


if __name__ == "__main__":
    main()
