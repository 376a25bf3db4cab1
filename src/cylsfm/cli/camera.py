"""``cylsfm camera``: write a ``camera.json`` (a full cylindrical or equirectangular panorama, or a centred
pinhole camera), or describe one."""

from __future__ import annotations

import argparse

from ..errors import InputError
from .base import command


def _camera_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True)
    show = sub.add_parser(
        "show",
        help="describe a camera.json: its model, size and intrinsics, and for a cylinder its horizontal field "
        "of view, whether it wraps around, and the elevations of its top and bottom rows",
    )
    show.add_argument("path", help="camera.json to read (a dataset sequence's, or one 'camera new' wrote)")
    new = sub.add_parser(
        "new",
        help="write the camera.json of a full 360-degree panorama (cylindrical by default) or a pinhole camera",
    )
    new.add_argument("path", help="camera.json to write")
    new.add_argument("--width", type=int, required=True, help="image width in pixels")
    new.add_argument("--height", type=int, required=True, help="image height in pixels")
    new.add_argument(
        "--model",
        choices=["cylindrical", "equirectangular", "pinhole"],
        default="cylindrical",
        help="cylindrical (default) or equirectangular: the full 360-degree panorama of that size; "
        "pinhole: a centred camera with square pixels and the horizontal field of view --hfov (or the focal "
        "length --focal)",
    )
    new.add_argument(
        "--vfov-h",
        type=float,
        default=1.0,
        help="cylindrical: rows span h in [-vfov_h, vfov_h] on the unit cylinder (1.0 = +-45 degrees of "
        "elevation)",
    )
    new.add_argument("--hfov", type=float, help="pinhole: horizontal field of view in degrees")
    new.add_argument(
        "--focal", type=float, metavar="PX", help="pinhole: focal length in pixels (instead of --hfov)"
    )


@command("camera", "write or describe a camera.json", _camera_args)
def run_camera(args: argparse.Namespace) -> int:
    import math

    from ..geometry import CylindricalCamera, load_camera

    if args.action == "new":
        cam = _new_camera(args)
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


def _new_camera(args: argparse.Namespace):
    """The camera ``cylsfm camera new`` describes."""
    import math

    from ..geometry import CylindricalCamera, EquirectangularCamera, PinholeCamera

    if args.model == "equirectangular":
        return EquirectangularCamera.full(args.width, args.height)
    if args.model == "pinhole":
        if (args.hfov is None) == (args.focal is None):
            raise InputError(
                "a pinhole camera needs its horizontal field of view (--hfov DEG) or its focal length (--focal PX)"
            )
        if args.focal is not None:
            if not args.focal > 0:
                raise InputError(f"--focal must be a positive number of pixels, got {args.focal}")
            hfov = 2 * math.degrees(math.atan(args.width / 2 / args.focal))
            return PinholeCamera.from_fov(args.width, args.height, hfov)
        return PinholeCamera.from_fov(args.width, args.height, args.hfov)
    return CylindricalCamera.full(args.width, args.height, args.vfov_h)
