"""``cylsfm evaluate depth|pose``: score a model (or another method's output) against ground truth.

The options are passed on as they are: :func:`~cylsfm.evaluate.depth.evaluate_depth` and
:func:`~cylsfm.evaluate.pose.evaluate_pose` check them (:class:`~cylsfm.errors.InputError`).
"""

from __future__ import annotations

import argparse

from .base import add_amp_argument, add_pose_iterations_argument, command


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
        _common_args(q)
    _depth_args(depth)
    _pose_args(pose)


def _common_args(q: argparse.ArgumentParser) -> None:
    q.add_argument("--data", required=True, help="dataset root (format v1) with ground truth")
    q.add_argument("--split", default="test", help="test | val | train | a split file | all (default: test)")
    q.add_argument("--split-name", default="default", help="split directory under ROOT/splits")
    q.add_argument("--json", help="write the results to this JSON file")
    q.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    add_amp_argument(q)
    q.add_argument("--batch-size", type=int, default=8, help="images per network call (default 8)")
    q.add_argument("--no-progress", action="store_true", help="no progress bars")


def _depth_args(depth: argparse.ArgumentParser) -> None:
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


def _pose_args(pose: argparse.ArgumentParser) -> None:
    pose.add_argument("--snippet", type=int, default=5, help="frames per ATE snippet (default 5)")
    add_pose_iterations_argument(pose)
    pose.add_argument(
        "--yaw-roll",
        type=int,
        metavar="SEED",
        help="roll each test sequence by a random yaw (seeded), turning the ground truth with it: as if the "
        "camera had been mounted turned about its vertical axis",
    )
    pose.add_argument("--stride", type=int, help="frame step (default: the model's; 1 for --trajectory)")
    pose.add_argument("--out", help="directory for the model's TUM trajectories and top-view plots")


def json_safe(value):
    """NaN and infinities -> None, recursively (strict JSON)."""
    import math

    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


@command(
    "evaluate", "score depth or ego-motion against ground truth, next to simple baselines", _evaluate_args
)
def run_evaluate(args: argparse.Namespace) -> int:
    import json

    from ..atomic import atomic_write_bytes

    source = None
    if args.checkpoint:
        from ..model import Predictor

        source = Predictor.from_checkpoint(
            args.checkpoint, args.device, getattr(args, "pose_iterations", None), args.amp
        )
    report = _depth(args, source) if args.action == "depth" else _pose(args, source)
    if args.json:
        text = json.dumps(json_safe(report), indent=2, allow_nan=False) + "\n"
        atomic_write_bytes(args.json, text.encode())
        print(f"wrote {args.json}")
    return 0


def _depth(args: argparse.Namespace, source) -> dict:
    """Run ``evaluate depth``, print its table; returns the JSON report."""
    from ..evaluate.depth import depth_json, evaluate_depth, format_depth_table

    result = evaluate_depth(
        source if source is not None else args.predictions,
        args.data,
        split=None if args.split == "all" else args.split,
        split_name=args.split_name,
        prior_split=None if args.prior_split == "all" else args.prior_split,
        min_depth=args.min_depth,
        max_depth=args.max_depth,
        median_scaling=not args.no_median_scaling,
        batch_size=args.batch_size,
        progress=None if not args.no_progress else False,
        seam_fraction=2 * args.seam_degrees / 360.0,
        yaw_roll=args.yaw_roll,
    )
    print(format_depth_table(result))
    return depth_json(result)


def _pose(args: argparse.Namespace, source) -> dict:
    """Run ``evaluate pose``, print its table; returns the JSON report."""
    from ..evaluate.pose import evaluate_pose, format_pose_table, pose_json

    result = evaluate_pose(
        source if source is not None else args.trajectory,
        args.data,
        split=None if args.split == "all" else args.split,
        split_name=args.split_name,
        snippet=args.snippet,
        stride=args.stride,
        out=args.out,
        batch_size=args.batch_size,
        progress=None if not args.no_progress else False,
        yaw_roll=args.yaw_roll,
    )
    print(format_pose_table(result))
    if args.out:
        print(f"trajectories and plots in {args.out}")
    return pose_json(result)
