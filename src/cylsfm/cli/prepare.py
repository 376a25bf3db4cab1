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
    _outputs(p)


def _outputs(p: argparse.ArgumentParser, preset: str = "paper", mode: str = "auto") -> None:
    """Options every source shares: the split written, --overwrite, --no-progress."""
    p.add_argument(
        "--split",
        type=parse_split,
        default=PRESETS[preset],
        metavar="TRAIN,VAL,TEST",
        help="write OUT/splits/default/ when it does not exist (default "
        f"{','.join(f'{10 * v:g}' for v in PRESETS[preset])}); 'none': no split files (see `cylsfm split`)",
    )
    p.add_argument(
        "--split-mode",
        choices=["auto", "sequence", "frame"],
        default=mode,
        help=f"auto: by sequence with 3 or more sequences, else by frame (the paper's rule); default {mode}",
    )
    p.add_argument("--overwrite", action="store_true", help="prepare again what was prepared before")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _band(p: argparse.ArgumentParser, size: str, vfov_h: float, why: str) -> None:
    p.add_argument("--size", type=parse_size, default=parse_size(size), help=f"output WxH (default {size})")
    p.add_argument(
        "--vfov-h",
        type=float,
        default=vfov_h,
        help=f"the band kept: h in [-vfov_h, vfov_h] on the unit cylinder (default {vfov_h:g}: {why})",
    )
    p.add_argument("--camera", help="camera.json of the output cylinder exactly (overrides --size, --vfov-h)")


def _prepare_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="source", required=True)
    eq = sub.add_parser(
        "equirect",
        help="equirectangular 360-degree videos (mp4, mkv, mov ...) or image folders -> cylindrical sequences",
    )
    _common(eq)
    _band(eq, "512x128", 1.0, "+-45 degrees of elevation, the paper's")
    eq.add_argument(
        "--mask",
        help="mask image of the helmet or mount (white: use), equirectangular or of the output's size",
    )
    fr = sub.add_parser("frames", help="folders of cylindrical panoramas already warped -> sequences")
    _common(fr)
    fr.add_argument("--camera", required=True, help="camera.json of the panoramas (cylindrical, their size)")
    fr.add_argument("--mask", help="mask image of the panoramas' size (white: use)")
    _headcam_args(sub)
    _views_args(sub)
    _synthia_args(sub)


def _headcam_args(sub) -> None:
    hc = sub.add_parser(
        "headcam", help="the paper's Headcam videos (ROOT/*.mkv, one per day) as it prepared them"
    )
    hc.add_argument("root", metavar="ROOT", help="folder of the dataset's videos")
    hc.add_argument("out", metavar="OUT", help="the dataset root: one sequence per video")
    hc.add_argument("--fps", type=float, default=5.0, help="frames a second taken (default 5, the paper's)")
    _band(hc, "512x128", 1.0, "+-45 degrees, the paper's")
    hc.add_argument("--mask", help="helmet mask (white: use), equirectangular or of the output's size")
    hc.add_argument(
        "--exclude",
        metavar="FILE",
        help="excluded-frames list: 'VIDEO NUMBER' (or VIDEO/NUMBER) a line, numbers counting 5 fps frames",
    )
    hc.add_argument(
        "--exclude-numbering",
        type=int,
        choices=[0, 1],
        default=0,
        help="the list's first frame: 0 (the original code's, default) or 1 (ffmpeg's %%05d file names)",
    )
    _outputs(hc, preset="headcam", mode="frame")


def _views_args(sub) -> None:
    vw = sub.add_parser(
        "views", help="pinhole views sharing a centre (cube faces, a camera rig) -> panoramas"
    )
    vw.add_argument("rig", metavar="RIG", help="rig.json: the views' folders, cameras and directions")
    vw.add_argument("out", metavar="OUT", help="the dataset root: the sequence OUT/NAME")
    vw.add_argument("--name", help="the sequence's name (default: the rig file's folder name)")
    _band(vw, "512x128", 1.0, "+-45 degrees; pixels no view sees are masked")
    vw.add_argument("--exclude", metavar="FILE", help="frames to leave out: one name per line")
    vw.add_argument(
        "--static-motion",
        type=float,
        default=0.0,
        metavar="METRES",
        help="leave out frames that moved less than this (and turned < 1 degree) by the rig's poses",
    )
    _outputs(vw)


def _synthia_args(sub) -> None:
    sy = sub.add_parser(
        "synthia", help="SYNTHIA-Seqs: four 90-degree views a frame stitched into 360 degrees"
    )
    sy.add_argument("root", metavar="ROOT", help="folder holding SYNTHIA-SEQS-NN-SEASON/ folders")
    sy.add_argument("out", metavar="OUT", help="the dataset root: sequences NN-SEASON-left|right")
    sy.add_argument("--sequences", nargs="+", metavar="NN", help="e.g. 02 05 (default: every one found)")
    sy.add_argument("--seasons", nargs="+", metavar="SEASON", help="e.g. spring summer fall (default: all)")
    sy.add_argument(
        "--stereo",
        nargs="+",
        choices=["left", "right"],
        default=["left", "right"],
        metavar="SIDE",
        help="which cameras of the stereo rig to prepare, left and/or right (default: both; each side "
        "becomes its own sequence NN-SEASON-SIDE)",
    )
    _band(sy, "512x128", 0.5, "the band all four views see")
    sy.add_argument(
        "--convention",
        default="auto",
        help="axes of the camera files: auto (default: the one whose poses best predict the frames), "
        "y-up, none, yz-flip, x-flip, each with -inv for world-to-camera files",
    )
    sy.add_argument(
        "--static-motion",
        type=float,
        default=0.1,
        metavar="METRES",
        help="leave out frames that moved less than this and turned < 1 degree (default 0.1; 0 keeps all)",
    )
    sy.add_argument("--no-depth", action="store_true", help="do not write the ground-truth depth")
    sy.add_argument("--exclude", metavar="FILE", help="frames to leave out: one name per line")
    _outputs(sy, mode="frame")


def _exclude(path: str | None) -> frozenset[str]:
    if path is None:
        return frozenset()
    from ..data.io import read_text

    names = (line.split("#", 1)[0].strip() for line in read_text(path, "exclude list").splitlines())
    return frozenset(n for n in names if n)


def _camera(args: argparse.Namespace):
    from ..geometry import CylindricalCamera, load_camera

    camera = load_camera(args.camera) if getattr(args, "camera", None) else None
    if camera is not None and not isinstance(camera, CylindricalCamera):
        raise InputError(f"{args.camera}: the output camera must be cylindrical, got {camera.model}")
    return camera


def _equirect_options(args: argparse.Namespace):
    from pathlib import Path

    from ..data.prepare import EquirectOptions

    return EquirectOptions(
        size=getattr(args, "size", (512, 128)),
        vfov_h=getattr(args, "vfov_h", 1.0),
        camera=_camera(args),
        fps=args.fps,
        start=getattr(args, "start", None),
        end=getattr(args, "end", None),
        mask=Path(args.mask) if args.mask else None,
        exclude=_exclude(args.exclude) if args.source != "headcam" else frozenset(),
        drop_static=getattr(args, "drop_static", 0.0),
    )


def _run_source(args: argparse.Namespace) -> list[str]:
    """Prepare what ``args`` asks for; one line a sequence for the user."""
    from ..data import prepare as prep

    progress = not args.no_progress
    if args.source == "views":
        camera = _camera(args)
        options = prep.RigOptions(args.size, args.vfov_h, camera, _exclude(args.exclude), args.static_motion)
        path, n, dropped = prep.prepare_views(
            args.rig, args.out, options, args.name, args.overwrite, progress
        )
        return [f"{path}: {n} frames" + (f", {dropped} left out as static" if dropped else "")]
    if args.source == "synthia":
        if _camera(args) is not None:
            raise InputError("prepare synthia takes --size and --vfov-h, not --camera")
        options = prep.SynthiaOptions(
            sequences=tuple(args.sequences) if args.sequences else None,
            seasons=tuple(args.seasons) if args.seasons else None,
            sides=tuple(args.stereo),
            size=args.size,
            vfov_h=args.vfov_h,
            convention=args.convention,
            static_motion=args.static_motion,
            depth=not args.no_depth,
            exclude=_exclude(args.exclude),
        )
        return [
            r.line() for r in prep.prepare_synthia(args.root, args.out, options, args.overwrite, progress)
        ]
    options = _equirect_options(args)
    if args.source == "headcam":
        reports = prep.prepare_headcam(
            args.root, args.out, options, args.exclude, args.exclude_numbering, args.overwrite, progress
        )
    elif args.source == "equirect":
        reports = prep.prepare_equirect(args.inputs, args.out, options, args.overwrite, progress)
    else:
        assert options.camera is not None
        reports = prep.prepare_frames(
            args.inputs, args.out, options.camera, options, args.overwrite, progress
        )
    return [r.line() for r in reports]


@command("prepare", "turn 360-degree footage into a dataset (sequences and splits)", _prepare_args)
def run_prepare(args: argparse.Namespace) -> int:
    from pathlib import Path

    for line in _run_source(args):
        print(line)
    if args.split is not None:
        _write_splits(Path(args.out), args.split, args.split_mode, args.overwrite)
    _warn_untrainable(Path(args.out))
    return 0


def _warn_untrainable(root) -> None:
    """A warning for panoramas that ``cylsfm train`` would refuse at their own size (full panoramas need
    widths that are multiples of 128 and heights of at least 32)."""
    import sys

    from ..data.format import scan_dataset
    from ..nn.layers import check_input_size

    for seq in scan_dataset(root):
        cam = seq.camera
        try:
            check_input_size(cam.width, cam.height, cam.wraps)
        except ValueError as exc:
            print(
                f"warning: {root / seq.name}: {cam.width}x{cam.height} panoramas: cylsfm train refuses this "
                f"size unless given another --size ({exc})",
                file=sys.stderr,
            )
            return


def _write_splits(root, fractions, mode: str, overwrite: bool) -> None:
    from ..data.format import scan_dataset
    from ..data.splits import SPLIT_PARTS, make_splits, split_path

    if not overwrite and any(split_path(root, part).exists() for part in SPLIT_PARTS):
        print(f"kept the split files in {root / 'splits' / 'default'}")
        return
    if mode == "auto":
        mode = "sequence" if len(scan_dataset(root)) >= 3 else "frame"
    paths = make_splits(root, mode=mode, fractions=fractions)
    print(f"wrote {paths['train'].parent}/{{train,val,test}}.txt (by {mode})")
