"""The ``cylsfm`` command: one entry point, one subcommand per job.

Subcommands register themselves in :data:`COMMANDS` with a function that adds their arguments and a
function that runs them; heavy imports happen inside the run functions so that ``cylsfm --help`` is fast.
Problems with the user's input (:class:`cylsfm.errors.CylsfmError`) are reported as one line naming the file
and the problem, with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass

from . import __version__
from .errors import CylsfmError


@dataclass(frozen=True)
class Command:
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int | None]


COMMANDS: dict[str, Command] = {}


def command(name: str, help: str, add_arguments: Callable[[argparse.ArgumentParser], None]):
    """Decorator registering ``run(args)`` as the subcommand ``name``."""

    def register(run: Callable[[argparse.Namespace], int | None]):
        COMMANDS[name] = Command(help, add_arguments, run)
        return run

    return register


# ----------------------------------------------------------------------------- camera
def _camera_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True)
    show = sub.add_parser("show", help="describe a camera.json")
    show.add_argument("path", help="camera.json to read")
    new = sub.add_parser("new", help="write the camera.json of a full 360-degree cylindrical panorama")
    new.add_argument("path", help="camera.json to write")
    new.add_argument("--width", type=int, required=True, help="panorama width in pixels")
    new.add_argument("--height", type=int, required=True, help="panorama height in pixels")
    new.add_argument(
        "--vfov-h",
        type=float,
        default=1.0,
        help="rows span h in [-vfov_h, vfov_h] on the unit cylinder (1.0 = +-45 degrees of elevation)",
    )


@command("camera", "write or describe a camera.json", _camera_args)
def _camera(args: argparse.Namespace) -> int:
    import math

    from .geometry import CylindricalCamera, load_camera

    if args.action == "new":
        cam = CylindricalCamera.full(args.width, args.height, args.vfov_h)
        cam.to_json(args.path)
        print(f"wrote {args.path}")
    else:
        cam = load_camera(args.path)
    print(f"model: {cam.model}, {cam.width}x{cam.height} px")
    print(f"fx={float(cam.fx):.6g} cx={float(cam.cx):.6g} fy={float(cam.fy):.6g} cy={float(cam.cy):.6g}")
    if isinstance(cam, CylindricalCamera):
        top = (-0.5 - float(cam.cy)) / float(cam.fy)
        bottom = (cam.height - 0.5 - float(cam.cy)) / float(cam.fy)
        print(
            f"horizontal field of view {cam.hfov_deg:.1f} deg ({'wraps' if cam.wraps else 'does not wrap'}), "
            f"elevation {-math.degrees(math.atan(top)):.1f} to {-math.degrees(math.atan(bottom)):.1f} deg"
        )
    return 0


# ----------------------------------------------------------------------------- synth
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
def _synth(args: argparse.Namespace) -> int:
    import time

    from .data.synthetic import SynthConfig, generate_dataset

    for name in ("sequences", "frames", "width", "height"):
        if getattr(args, name) < 1:
            raise CylsfmError(f"--{name} must be at least 1, got {getattr(args, name)}")
    if args.frames < 3:
        raise CylsfmError(f"--frames must be at least 3 (a target and two sources), got {args.frames}")
    from pathlib import Path

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


# ----------------------------------------------------------------------------- demo
def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", help="output directory (default: demo_out)")
    p.add_argument("--minutes", type=float, default=1.0, help="training time budget in minutes")
    p.add_argument("--seed", type=int, default=0)


@command("demo", "the main job: a self-contained demonstration on built-in synthetic data", _demo_args)
def _demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    run_demo(args.out, minutes=args.minutes, seed=args.seed)
    return 0


# ----------------------------------------------------------------------------- entry point
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cylsfm",
        description="Self-supervised depth and ego-motion from 360-degree cylindrical panoramic video.",
    )
    parser.add_argument("--version", action="version", version=f"cylsfm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, cmd in COMMANDS.items():
        p = sub.add_parser(name, help=cmd.help, description=cmd.help)
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    try:
        return int(args._run(args) or 0)
    except CylsfmError as exc:
        print(f"cylsfm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cylsfm {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
