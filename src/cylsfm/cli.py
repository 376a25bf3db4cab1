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
