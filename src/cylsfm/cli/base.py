"""The registry of ``cylsfm`` subcommands and the argument types they share.

Each command module registers itself with :func:`command`: a function that adds its arguments to its
``argparse`` parser, and a function that runs it. Run functions import what they need when they run, so
that ``cylsfm --help`` starts fast.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["COMMANDS", "Command", "command", "parse_size"]


@dataclass(frozen=True)
class Command:
    """One subcommand: its one-line help, its argument builder and its run function."""

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int | None]


#: The subcommands by name, in the order ``cylsfm --help`` lists them.
COMMANDS: dict[str, Command] = {}


def command(name: str, help: str, add_arguments: Callable[[argparse.ArgumentParser], None]):
    """Decorator registering ``run(args)`` as the subcommand ``name``."""

    def register(run: Callable[[argparse.Namespace], int | None]):
        COMMANDS[name] = Command(help, add_arguments, run)
        return run

    return register


def parse_size(text: str) -> tuple[int, int]:
    """``"512x128"`` -> ``(512, 128)`` (width, height in pixels); an ``argparse`` type."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 512x128, got {text!r}") from None
    return w, h


def add_pose_iterations_argument(p: argparse.ArgumentParser) -> None:
    """``--pose-iterations N`` (``args.pose_iterations``; ``None``: the network's own default)."""
    p.add_argument(
        "--pose-iterations",
        type=int,
        help="passes of the pose network over each source warped by its current pose, after the first "
        "(default: 3 for a pair pose network, 0 for the paper's one-pass network)",
    )


def add_amp_argument(p: argparse.ArgumentParser) -> None:
    """``--no-amp``: the networks in fp32 (``args.amp`` False); default bf16 where it is native."""
    p.add_argument(
        "--no-amp",
        dest="amp",
        action="store_false",
        help="networks in fp32 (default: bf16 where native: CPUs with AVX-512 BF16 or AMX, CUDA GPUs)",
    )
