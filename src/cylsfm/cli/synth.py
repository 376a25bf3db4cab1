"""``cylsfm synth``: the built-in synthetic 360-degree street benchmark, with ground truth."""

from __future__ import annotations

import argparse

from ..errors import CylsfmError
from .base import command


def _synth_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="output dataset root (sequences go to OUT/seq_NNN)")
    p.add_argument(
        "--sequences", type=int, default=4, help="number of rides, each in its own town (default 4)"
    )
    p.add_argument("--frames", type=int, default=200, help="frames per ride (default 200, about 1 m apart)")
    p.add_argument("--width", type=int, default=512, help="image width (default 512)")
    p.add_argument("--height", type=int, default=128, help="image height (default 128)")
    p.add_argument("--seed", type=int, default=0, help="seed: the same seed gives the same dataset")
    p.add_argument("--moving-objects", action="store_true", help="add cars driving along the streets")
    p.add_argument(
        "--projection",
        choices=["cylindrical", "equirect", "pinhole"],
        default="cylindrical",
        help="cylindrical panoramas (default), equirectangular panoramas or 90-degree pinhole views",
    )
    p.add_argument("--first-index", type=int, default=0, help="number the sequences from this index")
    p.add_argument("--workers", type=int, default=None, help="render processes (default: one per CPU)")
    p.add_argument(
        "--supersample", type=int, default=1, help="1: quincunx anti-aliasing; n: n x n rays a pixel"
    )
    p.add_argument("--overwrite", action="store_true", help="replace sequences that already exist in OUT")


@command(
    "synth", "generate the built-in synthetic 360-degree street benchmark (with ground truth)", _synth_args
)
def run_synth(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from ..data.synthetic import SynthConfig, generate_dataset

    for name in ("sequences", "frames", "width", "height"):
        if getattr(args, name) < 1:
            raise CylsfmError(f"--{name} must be at least 1, got {getattr(args, name)}")
    if args.frames < 3:
        raise CylsfmError(f"--frames must be at least 3 (a target and two sources), got {args.frames}")
    existing = [
        Path(args.out) / f"seq_{n:03d}" for n in range(args.first_index, args.first_index + args.sequences)
    ]
    existing = [d for d in existing if (d / "camera.json").exists() or (d / "images").is_dir()]
    if existing and not args.overwrite:
        raise CylsfmError(f"{existing[0]}: already holds a sequence (use --overwrite to replace it)")
    t0 = time.monotonic()
    dirs = generate_dataset(
        args.out,
        sequences=args.sequences,
        frames=args.frames,
        width=args.width,
        height=args.height,
        seed=args.seed,
        moving_objects=args.moving_objects,
        projection=args.projection,
        workers=args.workers,
        config=SynthConfig(supersample=args.supersample),
        first_index=args.first_index,
        overwrite=args.overwrite,
    )
    n = args.sequences * args.frames
    dt = time.monotonic() - t0
    print(f"wrote {len(dirs)} sequences, {n} frames to {args.out} in {dt:.1f} s ({n / dt:.1f} frames/s)")
    return 0
