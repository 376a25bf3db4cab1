"""``cylsfm demo``: the main job: generate data, train, evaluate and report, on built-in synthetic data."""

from __future__ import annotations

import argparse

from .base import command, parse_size


def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", help="output directory (default: demo_out)")
    p.add_argument("--minutes", type=float, default=20.0, help="total time budget in minutes (default 20)")
    p.add_argument("--seed", type=int, default=0, help="seed of the data and of training (default 0)")
    p.add_argument("--size", type=parse_size, default=(256, 64), help="training size WxH (default 256x64)")
    p.add_argument("--sequences", type=int, default=16, help="synthetic rides to generate (default 16)")
    p.add_argument("--test-sequences", type=int, default=3, help="of which held out for testing (default 3)")
    p.add_argument("--frames", type=int, default=150, help="frames per ride (default 150)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


@command(
    "demo", "the main job: generate data, train, evaluate and report, on built-in synthetic data", _demo_args
)
def run_demo_command(args: argparse.Namespace) -> int:
    from ..demo import run_demo

    run_demo(
        args.out,
        minutes=args.minutes,
        seed=args.seed,
        width=args.size[0],
        height=args.size[1],
        sequences=args.sequences,
        test_sequences=args.test_sequences,
        frames=args.frames,
        progress=not args.no_progress,
    )
    return 0
