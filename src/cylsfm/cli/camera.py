"""``cylsfm camera``: write the ``camera.json`` of a full panorama, or describe one."""

from __future__ import annotations

import argparse

from .base import command


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
def run_camera(args: argparse.Namespace) -> int:
    import math

    from ..geometry import CylindricalCamera, load_camera

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
