"""``cylsfm prepare``: footage as dataset sequences (equirectangular 360-degree video and images, or
cylindrical panoramas already warped), with split files."""

from __future__ import annotations

import argparse

from ..errors import InputError
from .base import command, parse_size
from .split import PRESETS
from .synth import parse_split


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", metavar="INPUT", nargs="+", help="video files or folders of frames")
    p.add_argument("out", metavar="OUT", help="the dataset root: one sequence OUT/NAME per input")
    p.add_argument("--fps", type=float, help="take about N frames a second from videos (the paper: 5)")
    p.add_argument(
        "--start", type=float, help="first frame to keep: seconds into a video, position in a folder"
    )
    p.add_argument("--end", type=float, help="last frame to keep: seconds into a video, position in a folder")
    p.add_argument("--exclude", metavar="FILE", help="frames to leave out: one name per line ('#' comments)")
    p.add_argument(
        "--drop-static",
        type=float,
        nargs="?",
        const=0.01,
        default=0.0,
        metavar="DIFF",
        help="leave out frames of a camera standing still: grey thumbnails differing from the last kept "
        "frame by less than DIFF on average (default when given: 0.01)",
    )
    p.add_argument(
        "--split",
        type=parse_split,
        default=PRESETS["paper"],
        metavar="TRAIN,VAL,TEST",
        help="write OUT/splits/default/ when it does not exist: by sequence with 3 or more sequences, else "
        "by frame (the paper's rule); default 8,1,1; 'none': no split files (see `cylsfm split`)",
    )
    p.add_argument("--overwrite", action="store_true", help="prepare again what was prepared before")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _prepare_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="source", required=True)
    eq = sub.add_parser(
        "equirect",
        help="equirectangular 360-degree videos (mp4, mkv, mov ...) or image folders -> cylindrical sequences",
    )
    _common(eq)
    eq.add_argument("--size", type=parse_size, default=(512, 128), help="output WxH (default 512x128)")
    eq.add_argument(
        "--vfov-h",
        type=float,
        default=1.0,
        help="the band kept: h in [-vfov_h, vfov_h] on the unit cylinder (default 1: +-45 degrees of "
        "elevation, the paper's)",
    )
    eq.add_argument(
        "--camera", help="camera.json of the output cylinder exactly (overrides --size and --vfov-h)"
    )
    eq.add_argument(
        "--mask",
        help="mask image of the helmet or mount (white: use), equirectangular or of the output's size",
    )
    fr = sub.add_parser("frames", help="folders of cylindrical panoramas already warped -> sequences")
    _common(fr)
    fr.add_argument("--camera", required=True, help="camera.json of the panoramas (cylindrical, their size)")
    fr.add_argument("--mask", help="mask image of the panoramas' size (white: use)")


def _exclude(path: str | None) -> frozenset[str]:
    if path is None:
        return frozenset()
    from ..data.io import read_text

    names = (line.split("#", 1)[0].strip() for line in read_text(path, "exclude list").splitlines())
    return frozenset(n for n in names if n)


@command("prepare", "turn 360-degree footage into a dataset (sequences and splits)", _prepare_args)
def run_prepare(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..data.prepare import EquirectOptions, prepare_equirect, prepare_frames
    from ..geometry import CylindricalCamera, load_camera

    camera = load_camera(args.camera) if args.camera else None
    if camera is not None and not isinstance(camera, CylindricalCamera):
        raise InputError(f"{args.camera}: the output camera must be cylindrical, got {camera.model}")
    options = EquirectOptions(
        size=getattr(args, "size", (512, 128)),
        vfov_h=getattr(args, "vfov_h", 1.0),
        camera=camera,
        fps=args.fps,
        start=args.start,
        end=args.end,
        mask=Path(args.mask) if args.mask else None,
        exclude=_exclude(args.exclude),
        drop_static=args.drop_static,
    )
    progress = not args.no_progress
    if args.source == "equirect":
        reports = prepare_equirect(args.inputs, args.out, options, args.overwrite, progress)
    else:
        assert camera is not None
        reports = prepare_frames(args.inputs, args.out, camera, options, args.overwrite, progress)
    for r in reports:
        print(r.line())
    if args.split is not None:
        _write_splits(Path(args.out), args.split, args.overwrite)
    return 0


def _write_splits(root, fractions, overwrite: bool) -> None:
    from ..data.format import scan_dataset
    from ..data.splits import SPLIT_PARTS, make_splits, split_path

    if not overwrite and any(split_path(root, part).exists() for part in SPLIT_PARTS):
        print(f"kept the split files in {root / 'splits' / 'default'}")
        return
    mode = "sequence" if len(scan_dataset(root)) >= 3 else "frame"
    paths = make_splits(root, mode=mode, fractions=fractions)
    print(f"wrote {paths['train'].parent}/{{train,val,test}}.txt (by {mode})")
