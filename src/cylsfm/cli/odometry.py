"""``cylsfm odometry``: the trajectory of a whole ride from a trained model, optionally refined."""

from __future__ import annotations

import argparse
import functools

from .base import add_amp_argument, add_pose_iterations_argument, command


def _odometry_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", metavar="INPUT", help="a video file, a folder of frames, or a dataset sequence")
    p.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    p.add_argument("--out", required=True, help="output directory (a killed run in it continues)")
    add_ride_options(p)
    p.add_argument("--depth", action="store_true", help="also write every frame's depth: OUT/depth/FRAME.npy")


def add_ride_options(p: argparse.ArgumentParser) -> None:
    """The options of the odometry of a ride, shared by ``cylsfm odometry`` and the exports of a ride."""
    p.add_argument(
        "--camera",
        help="camera.json of the frames (cylindrical, equirectangular, pinhole); default: a dataset "
        "sequence's own, else a full cylinder of the model's aspect ratio or, for frames twice as wide "
        "as high, a full equirectangular panorama",
    )
    p.add_argument(
        "--refine",
        action="store_true",
        help="refine every step by direct photometric alignment with the depth (coarse to fine, robust)",
    )
    p.add_argument(
        "--depth-from",
        metavar="DATASET",
        help="with --refine: align with this dataset's ground-truth depth instead of the network's "
        "(a test of the refinement; the result is in metres)",
    )
    p.add_argument(
        "--camera-height",
        type=float,
        metavar="METRES",
        help="the camera's height above the ground: the trajectory (and depth maps) in metres",
    )
    p.add_argument("--steady-height", action="store_true", help="a camera at one height: steps in its unit")
    p.add_argument(
        "--keyframes",
        type=int,
        default=1,
        metavar="N",
        help="with --refine: align each frame to a keyframe, a new one every N frames (default 1: each frame "
        "to the previous one); errors then add up once per keyframe instead of once per frame",
    )
    p.add_argument(
        "--mount-yaw",
        default="auto",
        metavar="auto|DEGREES",
        help="where the camera's direction of travel lies in the panorama, in degrees of azimuth (0: straight "
        "ahead, 90: to the right, i.e. a camera mounted turned left); the pose network reads the frames "
        "turned to face the motion. Default auto: found from the first frames (full-panorama models)",
    )
    m = p.add_mutually_exclusive_group()
    m.add_argument(
        "--mask",
        metavar="IMAGE",
        help="white where the frames see the scene, black on the camera's own mount or helmet (the frames' "
        "geometry, any size of their aspect ratio): left out of the compass, --refine and the search for "
        "the direction of travel. Default: a dataset sequence's own mask.png",
    )
    m.add_argument("--no-mask", action="store_true", help="use every pixel, even where mask.png says not to")
    _closure_options(p)
    p.add_argument("--fps", type=float, help="take about N frames a second from a video (default: all)")
    p.add_argument("--stride", type=int, default=1, help="take every N-th frame (default 1)")
    p.add_argument("--batch-size", type=int, default=8, help="windows and pairs per call (default 8)")
    add_pose_iterations_argument(p)
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    add_amp_argument(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _closure_options(p: argparse.ArgumentParser) -> None:
    """Loop closure and the bundle adjustment, the stages after the tracking."""
    lp = p.add_mutually_exclusive_group()
    lp.add_argument(
        "--loops",
        dest="loops",
        action="store_const",
        const=True,
        default="auto",
        help="close loops: find the places the ride comes back to (a heading-invariant descriptor, verified "
        "by direct alignment both ways) and optimise the whole ride with them (a pose graph that also "
        "corrects the scale's drift). Default: on for rides of at least 200 frames with a full-panorama model",
    )
    lp.add_argument("--no-loops", dest="loops", action="store_const", const=False, help="never close loops")
    bp = p.add_mutually_exclusive_group()
    bp.add_argument(
        "--bundle",
        dest="bundle",
        action="store_const",
        const=True,
        default="auto",
        help="after the loops, adjust the poses together with sparse points: SIFT features of every frame at "
        "its own resolution, matched with the next frames under the odometry's guidance, triangulated and "
        "bundle-adjusted with the odometry's steps as priors (its scale kept). Default: on with --refine",
    )
    bp.add_argument(
        "--no-bundle",
        dest="bundle",
        action="store_const",
        const=False,
        help="never adjust (the refined steps)",
    )


def _mount(value: str) -> float | str:
    try:
        return value if value == "auto" else float(value)
    except ValueError:
        return value  # OdometrySettings names the problem


def _cell(m: dict, key: str, fmt: str = "9.4f") -> str:
    v = m.get(key)
    return format(v, fmt) if isinstance(v, float) else format("-", ">" + fmt.split(".")[0] + "s")


def _print_metrics(metrics: dict) -> None:
    print(
        f"{'':20s} {'APE rmse':>9s} {'RPE trans':>9s} {'RPE rot':>8s} {'rot err/frame':>13s} {'dir err':>8s}"
    )
    for name, m in metrics.items():
        f = functools.partial(_cell, m)
        print(
            f"{name:20s} {f('ape_rmse')} {f('rpe_trans_rmse')} {f('rpe_rot_deg_rmse', '8.3f')} "
            f"{f('rot_err_deg_mean', '13.3f')} {f('dir_err_deg_mean', '8.2f')}"
        )


@command(
    "odometry",
    "the trajectory of a whole ride (video, frames, dataset sequence), optionally refined",
    _odometry_args,
)
def run_odometry(args: argparse.Namespace) -> int:
    from ..odometry import odometry

    result = odometry(args.input, args.checkpoint, args.out, ride_settings(args, depth=args.depth))
    n = len(result.c2w)
    print(
        f"wrote {result.trajectory} ({n} frames, {result.unit}) in {result.seconds:.1f} s ({n / max(result.seconds, 1e-9):.1f} frames/s)"
    )
    if result.loops is not None:
        print(
            f"loops: {result.loops['verified']} candidate pairs verified, {result.loops['accepted']} accepted"
        )
    if result.bundle is not None:
        b = result.bundle
        seconds = sum(v for k, v in b.items() if k.endswith("_seconds"))
        print(
            f"bundle adjustment: {b['points']:.0f} points from {b['features_per_frame']:.0f} features a frame, "
            f"{b['kept']:.0f} of {b['observations']:.0f} observations kept, {seconds:.1f} s"
        )
    if result.metrics:
        print("against the ground truth (APE: Sim(3)-aligned; metres, degrees):")
        _print_metrics(result.metrics)
    return 0


def ride_settings(args: argparse.Namespace, depth: bool = False):
    """The :class:`~cylsfm.odometry.OdometrySettings` of the options of :func:`add_ride_options`;
    ``depth``: write every frame's depth."""
    from ..odometry import OdometrySettings

    return OdometrySettings(
        camera=args.camera,
        refine=args.refine,
        depth_from=args.depth_from,
        camera_height=args.camera_height,
        steady_height=args.steady_height,
        save_depth_maps=depth,
        fps=args.fps,
        stride=args.stride,
        keyframe_every=args.keyframes,
        mount_yaw=_mount(args.mount_yaw),
        batch_size=args.batch_size,
        device=args.device,
        amp=args.amp,
        progress=not args.no_progress,
        pose_iterations=args.pose_iterations,
        mask=False if args.no_mask else args.mask,
        loops=args.loops,
        bundle=args.bundle,
    )
