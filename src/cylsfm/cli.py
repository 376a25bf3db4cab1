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


# ----------------------------------------------------------------------------- train
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 512x128, got {text!r}") from None
    return w, h


def _train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="dataset root (format v1 or the original SfMLearner strips)")
    p.add_argument("--out", required=True, help="run directory (config, checkpoints, logs)")
    p.add_argument("--config", help="YAML file: a preset name and any fields to change")
    p.add_argument("--preset", help="paper-synthia | paper-headcam | improved | default")
    p.add_argument("--size", type=_size, help="training size WxH (e.g. 512x128)")
    p.add_argument("--batch-size", type=int)
    p.add_argument("--max-steps", type=int)
    p.add_argument("--minutes", type=float, help="wall-clock budget; stops with a checkpoint when spent")
    p.add_argument("--wrap", action=argparse.BooleanOptionalAction, default=None, help="wrap-around on/off")
    p.add_argument(
        "--fov", type=float, help="train on the centred crop of this many degrees (no wrap below 360)"
    )
    p.add_argument("--pose-head", choices=["mean", "equivariant"])
    p.add_argument(
        "--roll", action=argparse.BooleanOptionalAction, default=None, help="random yaw-roll augmentation"
    )
    p.add_argument(
        "--reverse",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="play half of the training snippets backwards (time-reversal augmentation)",
    )
    p.add_argument("--mask", help="static mask image: white = pixels to use (e.g. without the helmet)")
    p.add_argument("--split", help="split to train on (train, val, test, a split file path, or 'all')")
    p.add_argument("--workers", type=int, help="data loader processes")
    p.add_argument("--seed", type=int)
    p.add_argument("--device", help="auto | cpu | cuda | cuda:N")
    p.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its latest checkpoint"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", help="further settings as key=value, e.g. loss.ssim_weight=0.85")


def train_config_from_args(args: argparse.Namespace):
    """The resolved training configuration of ``cylsfm train`` arguments."""
    from .model.config import apply_overrides, load_config, preset

    cfg = load_config(args.config) if args.config else preset(args.preset or "default")
    if args.config and args.preset:
        cfg = apply_overrides(preset(args.preset), [])  # an explicit preset replaces the file's
    items = list(args.overrides or [])
    flag_map = {
        "data": "data.root",
        "batch_size": "batch_size",
        "max_steps": "max_steps",
        "minutes": "minutes",
        "wrap": "model.wrap",
        "fov": "data.fov",
        "pose_head": "model.pose_head",
        "roll": "data.roll",
        "reverse": "data.reverse",
        "mask": "data.mask",
        "workers": "data.workers",
        "seed": "seed",
        "device": "device",
    }
    pre = []
    for name, key in flag_map.items():
        value = getattr(args, name, None)
        if value is not None:
            pre.append(f"{key}={value}" if not isinstance(value, str) else f"{key}='{value}'")
    if args.size:
        pre += [f"data.width={args.size[0]}", f"data.height={args.size[1]}"]
    if args.split:
        pre.append("data.split=null" if args.split == "all" else f"data.split='{args.split}'")
    return apply_overrides(cfg, pre + items)


@command("train", "train depth and pose networks on panoramic video, without labels", _train_args)
def _train(args: argparse.Namespace) -> int:
    from .train.trainer import train

    cfg = train_config_from_args(args)
    if not cfg.data.root:
        raise CylsfmError("no training data: pass --data ROOT (or data.root in --config)")
    summary = train(cfg, args.out, resume=args.resume, progress=not args.no_progress)
    print(
        f"trained to step {summary['steps']} ({summary['stopped']}) in {summary['seconds'] / 60:.1f} min; "
        f"checkpoints in {args.out}/checkpoints"
    )
    return 0


# ----------------------------------------------------------------------------- predict
def _predict_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image files, folders of images, videos")
    p.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    p.add_argument("--out", required=True, help="output directory: OUT/NAME/FRAME.npy|png, OUT/NAME.mp4")
    p.add_argument(
        "--camera",
        help="camera.json of the inputs (cylindrical, equirectangular or pinhole); without it inputs must be "
        "full 360-degree cylindrical panoramas of the model's aspect ratio",
    )
    p.add_argument("--batch-size", type=int, default=8, help="frames per network call (default 8)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--no-png", action="store_true", help="do not write coloured depth pictures")
    p.add_argument("--fps", type=float, help="take about N frames a second from videos (default: all)")


@command("predict", "depth maps for panoramic images, folders and videos with a trained model", _predict_args)
def _predict(args: argparse.Namespace) -> int:
    from .predict import predict

    summary = predict(
        args.checkpoint,
        args.inputs,
        args.out,
        camera=args.camera,
        batch_size=args.batch_size,
        device=args.device,
        png=not args.no_png,
        fps=args.fps,
    )
    videos = f" and {len(summary.videos)} preview video(s)" if summary.videos else ""
    print(f"wrote {summary.total} depth maps of {len(summary.frames)} input(s){videos} to {args.out}")
    return 0


# ----------------------------------------------------------------------------- evaluate
def _evaluate_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True, metavar="{depth,pose}")
    depth = sub.add_parser(
        "depth",
        help="depth errors (Eigen et al., median scaling) against ground truth, with baselines",
        description="Depth errors (Eigen et al., median scaling) of a model or of another method's "
        "predictions against a dataset's ground truth, next to the constant and per-row baselines.",
    )
    src = depth.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="checkpoint file or run directory")
    src.add_argument(
        "--predictions",
        help="directory of depth maps PRED/SEQ/FRAME.npy (or PRED/SEQ/depth/FRAME.npy), any resolution",
    )
    pose = sub.add_parser(
        "pose",
        help="snippet ATE and full-trajectory APE/RPE (evo) against ground-truth poses, with baselines",
        description="Ego-motion: SfMLearner's snippet ATE and full-trajectory APE/RPE (Sim(3)-aligned, with "
        "evo) of a model or of another method's TUM trajectories, next to the zero-motion and "
        "constant-velocity baselines.",
    )
    src = pose.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="checkpoint file or run directory")
    src.add_argument(
        "--trajectory",
        help="TUM trajectories (camera-to-world) of another method: a directory with SEQ.txt per sequence, "
        "or one file for a single sequence",
    )
    for q in (depth, pose):
        q.add_argument("--data", required=True, help="dataset root (format v1) with ground truth")
        q.add_argument(
            "--split", default="test", help="test | val | train | a split file | all (default: test)"
        )
        q.add_argument("--split-name", default="default", help="split directory under ROOT/splits")
        q.add_argument("--json", help="write the results to this JSON file")
        q.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
        q.add_argument("--batch-size", type=int, default=8, help="images per network call (default 8)")
        q.add_argument("--no-progress", action="store_true", help="no progress bars")
    depth.add_argument(
        "--prior-split",
        default="train",
        help="frames of the per-row prior (default: train; 'all': every frame)",
    )
    depth.add_argument("--min-depth", type=float, default=1e-3, help="valid ground truth above (m)")
    depth.add_argument("--max-depth", type=float, default=80.0, help="valid ground truth below (m)")
    depth.add_argument(
        "--no-median-scaling", action="store_true", help="score the model's depth as it is (metric methods)"
    )
    depth.add_argument(
        "--seam-degrees",
        type=float,
        default=22.5,
        help="also score full panoramas within this azimuth of the seam, at each side (default 22.5; 0: off)",
    )
    depth.add_argument(
        "--yaw-roll",
        type=int,
        metavar="SEED",
        help="roll every test panorama and its ground truth by a random yaw (seeded, per frame): as if the "
        "camera had been turned about its vertical axis",
    )
    pose.add_argument("--snippet", type=int, default=5, help="frames per ATE snippet (default 5)")
    pose.add_argument(
        "--yaw-roll",
        type=int,
        metavar="SEED",
        help="roll each test sequence by a random yaw (seeded), turning the ground truth with it: as if the "
        "camera had been mounted turned about its vertical axis",
    )
    pose.add_argument("--stride", type=int, help="frame step (default: the model's; 1 for --trajectory)")
    pose.add_argument("--out", help="directory for the model's TUM trajectories and top-view plots")


def _json_safe(value):
    """NaN and infinities -> None, recursively (strict JSON)."""
    import math

    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


@command(
    "evaluate", "score depth or ego-motion against ground truth, next to simple baselines", _evaluate_args
)
def _evaluate(args: argparse.Namespace) -> int:
    import json

    from .atomic import atomic_write_bytes

    if args.batch_size < 1:
        raise CylsfmError(f"--batch-size must be at least 1, got {args.batch_size}")
    split = None if args.split == "all" else args.split
    progress = None if not args.no_progress else False
    if args.yaw_roll is not None and not args.checkpoint:
        raise CylsfmError("--yaw-roll rolls the input of a model: it needs --checkpoint")
    if args.checkpoint:
        from .model import Predictor

        source = Predictor.from_checkpoint(args.checkpoint, args.device)
    if args.action == "depth":
        from .evaluate.depth import depth_json, evaluate_depth, format_depth_table

        if not 0 < args.min_depth < args.max_depth:
            raise CylsfmError(
                f"need 0 < --min-depth < --max-depth, got {args.min_depth} and {args.max_depth}"
            )
        if not 0 <= args.seam_degrees <= 180:
            raise CylsfmError(f"--seam-degrees must be in [0, 180], got {args.seam_degrees}")
        result = evaluate_depth(
            source if args.checkpoint else args.predictions,
            args.data,
            split=split,
            split_name=args.split_name,
            prior_split=None if args.prior_split == "all" else args.prior_split,
            min_depth=args.min_depth,
            max_depth=args.max_depth,
            median_scaling=not args.no_median_scaling,
            batch_size=args.batch_size,
            progress=progress,
            seam_fraction=2 * args.seam_degrees / 360.0,
            yaw_roll=args.yaw_roll,
        )
        print(format_depth_table(result))
        report = depth_json(result)
    else:
        from .evaluate.pose import evaluate_pose, format_pose_table, pose_json

        if args.snippet < 2:
            raise CylsfmError(f"--snippet must be at least 2, got {args.snippet}")
        if args.stride is not None and args.stride < 1:
            raise CylsfmError(f"--stride must be at least 1, got {args.stride}")
        result = evaluate_pose(
            source if args.checkpoint else args.trajectory,
            args.data,
            split=split,
            split_name=args.split_name,
            snippet=args.snippet,
            stride=args.stride,
            out=args.out,
            batch_size=args.batch_size,
            progress=progress,
            yaw_roll=args.yaw_roll,
        )
        print(format_pose_table(result))
        if args.out:
            print(f"trajectories and plots in {args.out}")
        report = pose_json(result)
    if args.json:
        text = json.dumps(_json_safe(report), indent=2, allow_nan=False) + "\n"
        atomic_write_bytes(args.json, text.encode())
        print(f"wrote {args.json}")
    return 0


# ----------------------------------------------------------------------------- demo
def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", help="output directory (default: demo_out)")
    p.add_argument("--minutes", type=float, default=20.0, help="total time budget in minutes (default 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", type=_size, default=(256, 64), help="training size WxH (default 256x64)")
    p.add_argument("--sequences", type=int, default=16, help="synthetic rides to generate (default 16)")
    p.add_argument("--test-sequences", type=int, default=3, help="of which held out for testing (default 3)")
    p.add_argument("--frames", type=int, default=150, help="frames per ride (default 150)")
    p.add_argument("--no-progress", action="store_true")


@command(
    "demo", "the main job: generate data, train, evaluate and report, on built-in synthetic data", _demo_args
)
def _demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    if args.sequences < args.test_sequences + 2:
        raise CylsfmError(
            f"--sequences must leave at least 2 rides for training and validation, got {args.sequences}"
        )
    run_demo(
        args.out,
        minutes=args.minutes,
        seed=args.seed,
        width=args.size[0],
        height=args.size[1],
        sequences=args.sequences,
        test_sequences=args.test_sequences,
        frames=args.frames,
        progress=not args.no_progress,
    )
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
