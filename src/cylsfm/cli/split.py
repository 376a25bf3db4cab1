"""``cylsfm split``: write the split files of a dataset (which targets train, validate and test)."""

from __future__ import annotations

import argparse

from ..errors import InputError
from .base import command

#: Named fractions ``(train, val, test)``: the paper's SYNTHIA split and the Headcam split (no validation).
PRESETS = {"paper": (0.8, 0.1, 0.1), "headcam": (0.9, 0.0, 0.1)}


def _split_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("root", metavar="ROOT", help="dataset root (sequences with camera.json and images/)")
    p.add_argument(
        "--mode",
        choices=["sequence", "frame"],
        default="sequence",
        help="sequence (default): whole sequences to each part; frame: targets drawn by frame, no frame of a "
        "test or validation snippet used in training (the paper's rule)",
    )
    p.add_argument(
        "--fractions",
        type=float,
        nargs=3,
        metavar=("TRAIN", "VAL", "TEST"),
        help="the parts' fractions, summing to 1 (default: --preset paper)",
    )
    p.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="paper",
        help="paper: 0.8 / 0.1 / 0.1 (SYNTHIA); headcam: 0.9 / 0 / 0.1 (default paper)",
    )
    p.add_argument("--name", default="default", help="split name: ROOT/splits/NAME/ (default 'default')")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--seq-length", type=int, default=3, help="frames per snippet, as for training (default 3)"
    )
    p.add_argument("--stride", type=int, default=1, help="frames between a snippet's frames (default 1)")
    p.add_argument("--force", action="store_true", help="replace split files that exist")


@command("split", "write a dataset's split files (train / val / test)", _split_args)
def run_split(args: argparse.Namespace) -> int:
    from ..data.splits import SPLIT_PARTS, make_splits, split_path

    fractions = tuple(args.fractions) if args.fractions else PRESETS[args.preset]
    existing = [split_path(args.root, part, args.name) for part in SPLIT_PARTS]
    if not args.force and any(p.exists() for p in existing):
        raise InputError(f"{existing[0].parent}: split files exist; --force replaces them")
    paths = make_splits(
        args.root,
        name=args.name,
        mode=args.mode,
        fractions=fractions,
        seed=args.seed,
        seq_length=args.seq_length,
        stride=args.stride,
    )
    counts = ", ".join(f"{part} {_targets(paths[part])}" for part in SPLIT_PARTS)
    print(f"wrote {paths['train'].parent}/{{train,val,test}}.txt ({args.mode} split, targets: {counts})")
    return 0


def _targets(path) -> int:
    """The number of targets listed in a split file."""
    lines = path.read_text(encoding="utf-8").splitlines()
    return sum(1 for line in lines if line.split("#", 1)[0].strip())
