"""``cylsfm train``: train the depth and pose networks on panoramic video, without labels.

The configuration is built in three layers: a base (``--config FILE``, ``--preset NAME``, or, when a run
is resumed with neither, the run's own ``RUN/config.yaml``; otherwise the default preset), then the
flags, then ``key=value`` overrides. A resumed run therefore keeps its data root, budget and every other
setting unless a flag or override changes it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import CylsfmError
from .base import command, parse_size

#: Flags that set one configuration field each: ``argparse`` destination -> configuration key.
FLAG_KEYS = {
    "data": "data.root",
    "batch_size": "batch_size",
    "max_steps": "max_steps",
    "minutes": "minutes",
    "sfm_rounds": "sfm.rounds",
    "wrap": "model.wrap",
    "fov": "data.fov",
    "pose_head": "model.pose_head",
    "compass": "model.compass",
    "antisymmetric": "model.antisymmetric",
    "mask": "data.mask",
    "workers": "data.workers",
    "seed": "seed",
    "device": "device",
}


def _train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="dataset root (format v1 or the original SfMLearner strips)")
    p.add_argument("--out", required=True, help="run directory (config, checkpoints, logs)")
    p.add_argument("--config", help="YAML file: a preset name and any fields to change")
    p.add_argument("--preset", help="default (the default) | improved | paper-synthia | paper-headcam")
    p.add_argument(
        "--size",
        type=parse_size,
        help="training size WxH (default 512x128); with wrap-around the width must be a multiple of 128 "
        "and the height at least 32",
    )
    p.add_argument("--batch-size", type=int, help="samples per step and process (default 4)")
    p.add_argument("--max-steps", type=int, help="steps to train (default 60000)")
    p.add_argument(
        "--minutes", type=float, help="wall-clock budget; stops with a checkpoint when spent (default: none)"
    )
    p.add_argument(
        "--sfm-rounds",
        type=int,
        help="learn from the rides' own geometry: this many rounds of odometry with the bundle adjustment over "
        "the training rides, each followed by training on with their adjusted points and poses as targets "
        "(within the same budget; default 0: plain self-supervision)",
    )
    p.add_argument("--wrap", action=argparse.BooleanOptionalAction, default=None, help="wrap-around on/off")
    p.add_argument(
        "--fov", type=float, help="train on the centred crop of this many degrees (no wrap below 360)"
    )
    p.add_argument(
        "--pose-head",
        choices=["mean", "equivariant", "auto"],
        help="auto (preset default's): equivariant on full panoramas, mean on crops; mean: the paper's",
    )
    p.add_argument(
        "--compass",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="add the visual compass's yaw (column shift between the panoramas) to the predicted pose "
        "(on in preset default)",
    )
    p.add_argument(
        "--antisymmetric",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="pose from frame pairs, g(target, source) - g(source, target), trained under a fading slot "
        "prior (on in preset default; --no-antisymmetric: a one-pass network, still with the compass and "
        "the equivariant head unless they are turned off)",
    )
    p.add_argument("--mask", help="static mask image: white = pixels to use (e.g. without the helmet)")
    p.add_argument("--split", help="split to train on (train, val, test, a split file path, or 'all')")
    p.add_argument(
        "--workers",
        type=int,
        help="data loader processes (default: 0 on the CPU with the frames cached in memory, else 2)",
    )
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--device", help="auto (default: CUDA when present) | cpu | cuda | cuda:N")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its latest checkpoint, with the settings in OUT/config.yaml "
        "(flags and key=value change them: e.g. a new --max-steps or --minutes)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="start the run in --out again: its checkpoints, metrics.jsonl and tb/ are removed (without it "
        "a run already there is refused; --resume continues it)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--print-config",
        action="store_true",
        help="print the resolved configuration (YAML, as saved in OUT/config.yaml) and exit",
    )
    p.add_argument("overrides", nargs="*", help="further settings as key=value, e.g. loss.ssim_weight=0.85")


def _base_config(args: argparse.Namespace):
    """The configuration the flags and overrides are applied to."""
    from ..model.config import load_config, preset

    if args.preset:  # an explicit preset replaces a --config file's settings
        return preset(args.preset)
    if args.config:
        return load_config(args.config)
    saved = Path(args.out) / "config.yaml"
    if getattr(args, "resume", False) and saved.exists():
        return load_config(saved, saved=True)
    return preset("default")


def train_config_from_args(args: argparse.Namespace):
    """The resolved :class:`~cylsfm.model.config.TrainConfig` of ``cylsfm train`` arguments."""
    from ..model.config import apply_overrides

    pre = []
    for name, key in FLAG_KEYS.items():
        value = getattr(args, name, None)
        if value is not None:
            pre.append(f"{key}={value}" if not isinstance(value, str) else f"{key}='{value}'")
    if args.size:
        pre += [f"data.width={args.size[0]}", f"data.height={args.size[1]}"]
    if args.split:
        pre.append("data.split=null" if args.split == "all" else f"data.split='{args.split}'")
    return apply_overrides(_base_config(args), pre + list(args.overrides or []))


@command("train", "train depth and pose networks on panoramic video, without labels", _train_args)
def run_train(args: argparse.Namespace) -> int:
    from ..train.trainer import train

    cfg = train_config_from_args(args)
    if args.print_config:
        import yaml

        from ..model.config import config_to_dict

        print(yaml.safe_dump(config_to_dict(cfg), sort_keys=False), end="")
        return 0
    if not cfg.data.root and not args.resume:
        raise CylsfmError("no training data: pass --data ROOT (or data.root in --config)")
    if args.resume and args.overwrite:
        raise CylsfmError("--resume continues a run and --overwrite starts it again: give one")
    if cfg.sfm.rounds > 0:
        from ..rounds import train_rounds

        done = train_rounds(
            cfg, args.out, resume=args.resume, progress=not args.no_progress, overwrite=args.overwrite
        )
        for stage in done["stages"]:
            more = (
                f"to step {stage['steps']}" if stage["stage"] == "train" else f"{len(stage['rides'])} rides"
            )
            print(f"  {stage['stage']}: {more}, {stage['seconds'] / 60:.1f} min")
        print(
            f"trained to step {done['steps']} in rounds ({done['stopped']}) in {done['seconds'] / 60:.1f} min"
        )
        return 0
    summary = train(
        cfg, args.out, resume=args.resume, progress=not args.no_progress, overwrite=args.overwrite
    )
    print(
        f"trained to step {summary['steps']} ({summary['stopped']}) in {summary['seconds'] / 60:.1f} min; "
        f"checkpoints in {args.out}/checkpoints"
    )
    return 0
