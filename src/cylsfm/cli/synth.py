"""``cylsfm synth``: the built-in synthetic 360-degree street benchmark, with ground truth."""

from __future__ import annotations

import argparse

from .base import command


def parse_split(text: str) -> tuple[float, float, float] | None:
    """``"8,1,1"`` -> the fractions ``(0.8, 0.1, 0.1)`` of sequences in train, val and test; ``"none"`` ->
    ``None``; an ``argparse`` type."""
    if text.strip().lower() == "none":
        return None
    try:
        weights = [float(v) for v in text.split(",")]
    except ValueError:
        weights = []
    if len(weights) != 3 or min(weights) < 0 or sum(weights) <= 0:
        raise argparse.ArgumentTypeError(
            f"--split must be three non-negative numbers TRAIN,VAL,TEST (e.g. 8,1,1) or 'none', got {text!r}"
        )
    total = sum(weights)
    return weights[0] / total, weights[1] / total, weights[2] / total


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
    p.add_argument(
        "--split",
        type=parse_split,
        default=(0.8, 0.1, 0.1),
        metavar="TRAIN,VAL,TEST",
        help="write the split OUT/splits/default/{train,val,test}.txt by sequence (whole rides held out), "
        "with the sequences of OUT in these proportions (default 8,1,1; 'none': no split files)",
    )
    p.add_argument(
        "--occluder",
        choices=["none", "helmet", "roof"],
        default="none",
        help="an object fixed to the camera, the same texture in the same pixels of every frame (helmet: a "
        "rider's head and shoulders and a mounting pole, 18%% of the panorama; roof: a car's roof, 35%%), "
        "with no ground-truth depth, and each sequence's mask.png leaving it out",
    )
    p.add_argument(
        "--route",
        choices=["random", "block", "eight", "back", "stairs"],
        default="random",
        help="the camera's route: a random walk with turns at intersections (default); rides that come back: "
        "once around a block or a figure eight around two (both end where they start), out along streets "
        "and the same streets back in the opposite direction; or a staircase of alternating turns that never "
        "passes a place twice. The routes other than random are fitted to the town: give about as many "
        "frames as the route is long in metres (a message says how many when no route fits)",
    )
    p.add_argument(
        "--town-frames",
        type=int,
        default=0,
        help="build each town as for rides of N frames (default: --frames): with --frames 150 the benchmark's "
        "towns, so that rides of other routes and lengths go through the same towns",
    )
    p.add_argument(
        "--alike",
        action="store_true",
        help="every building of a town in one colour and one facade style: streets that look alike",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace sequences (and the split) that already exist in OUT"
    )


@command(
    "synth", "generate the built-in synthetic 360-degree street benchmark (with ground truth)", _synth_args
)
def run_synth(args: argparse.Namespace) -> int:
    import time

    from ..data.synth import SynthConfig, generate_dataset

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
        config=SynthConfig(
            supersample=args.supersample, route=args.route, town_frames=args.town_frames, alike=args.alike
        ),
        first_index=args.first_index,
        overwrite=args.overwrite,
        splits=args.split is not None,
        split_fractions=args.split or (0.8, 0.1, 0.1),
        occluder=args.occluder,
    )
    n = args.sequences * args.frames
    dt = time.monotonic() - t0
    print(f"wrote {len(dirs)} sequences, {n} frames to {args.out} in {dt:.1f} s ({n / dt:.1f} frames/s)")
    if args.split is not None:
        print(f"split by sequence: {args.out}/splits/default/{{train,val,test}}.txt")
    return 0
