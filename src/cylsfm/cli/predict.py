"""``cylsfm predict``: depth maps for panoramic images, folders and videos with a trained model."""

from __future__ import annotations

import argparse

from .base import add_amp_argument, command


def _predict_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image files, folders of images, videos")
    p.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    p.add_argument("--out", required=True, help="output directory: OUT/NAME/FRAME.npy|png, OUT/NAME.mp4")
    p.add_argument(
        "--camera",
        help="camera.json of the inputs (cylindrical, equirectangular or pinhole). Without it an input of the "
        "model's aspect ratio is taken as a full 360-degree cylindrical panorama, and a 2:1 input as an "
        "equirectangular 360-degree panorama (unless the model's own aspect is 2:1); any other input is "
        "refused. Inputs that are not full panoramas (pinhole photographs, partial panoramas) are taken "
        "only when they cover the view of a model trained on crops (train --fov)",
    )
    p.add_argument(
        "--mask",
        metavar="IMAGE",
        help="white where the inputs see the scene, black on the camera's own mount or helmet (the inputs' "
        "aspect ratio): the network sees it filled, its depth is written as 0 (unknown)",
    )
    p.add_argument("--batch-size", type=int, default=8, help="frames per network call (default 8)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    add_amp_argument(p)
    p.add_argument(
        "--no-png", action="store_true", help="do not write the pictures (input and coloured depth)"
    )
    p.add_argument(
        "--full-resolution",
        action="store_true",
        help="also write FRAME_full.npy/.png: the depth in the input's own camera and size "
        "(equirectangular input: equirectangular depth)",
    )
    p.add_argument("--fps", type=float, help="take about N frames a second from videos (default: all)")
    p.add_argument(
        "--camera-height",
        type=float,
        metavar="METRES",
        help="depth in metres: the camera's height above a level ground sets one factor for all frames of "
        "an input (fitted in up to 32 of its frames); default: the network's units. OUT/NAME/scale.json "
        "says which",
    )
    p.add_argument(
        "--odometry",
        metavar="DIR",
        help="the one input's output of cylsfm odometry --refine --depth (same checkpoint and --fps): every "
        "frame's depth in the trajectory's scale and unit, brought to the adjusted points it sees (the "
        "network's own scale wanders by several percent from frame to frame)",
    )


@command("predict", "depth maps for panoramic images, folders and videos with a trained model", _predict_args)
def run_predict(args: argparse.Namespace) -> int:
    from ..predict import predict

    summary = predict(
        args.checkpoint,
        args.inputs,
        args.out,
        camera=args.camera,
        batch_size=args.batch_size,
        device=args.device,
        amp=args.amp,
        png=not args.no_png,
        full_resolution=args.full_resolution,
        fps=args.fps,
        mask=args.mask,
        camera_height=args.camera_height,
        odometry=args.odometry,
    )
    videos = f" and {len(summary.videos)} preview video(s)" if summary.videos else ""
    kept = f" ({summary.resumed} of them kept from an interrupted run)" if summary.resumed else ""
    print(f"wrote {summary.total} depth maps of {len(summary.frames)} input(s){videos} to {args.out}{kept}")
    return 0
