"""The ``cylsfm`` command: one entry point, one subcommand per job, one module per subcommand.

Subcommands register themselves in :data:`~cylsfm.cli.base.COMMANDS` (``camera``, ``prepare``, ``synth``, ``split``, ``train``,
``predict``, ``odometry``, ``evaluate``, ``export``, ``demo``); heavy imports happen inside their run functions so that
``cylsfm --help`` is fast. Problems with the user's input (:class:`cylsfm.errors.CylsfmError`, which the
library raises for invalid arguments too) are reported as one line naming the file and the problem, with
exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from .._version import __version__
from ..errors import CylsfmError
from . import camera, demo, evaluate, export, odometry, predict, prepare, split, synth, train  # noqa: F401  (register the subcommands)
from .base import COMMANDS, Command, command, parse_size
from .train import train_config_from_args

#: The order in which ``cylsfm --help`` lists the subcommands: the order of the work.
ORDER = ("camera", "prepare", "synth", "split", "train", "predict", "odometry", "evaluate", "export", "demo")

__all__ = ["COMMANDS", "Command", "build_parser", "command", "main", "parse_size", "train_config_from_args"]


def build_parser() -> argparse.ArgumentParser:
    """The ``cylsfm`` argument parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="cylsfm",
        description="Self-supervised depth and ego-motion from 360-degree cylindrical panoramic video.",
    )
    parser.add_argument("--version", action="version", version=f"cylsfm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in sorted(COMMANDS, key=lambda n: ORDER.index(n) if n in ORDER else len(ORDER)):
        cmd = COMMANDS[name]
        p = sub.add_parser(name, help=cmd.help, description=cmd.help)
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler preempting the job): handled as Ctrl-C is."""


def _terminate(signum: int, frame: object) -> None:
    raise Terminated


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM interrupts like Ctrl-C: every command stops the way it stops for Ctrl-C
    (its outputs consistent on disk, resumable where the command resumes). ``cylsfm train`` installs its
    own handler while it trains (a checkpoint at the step in progress)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _Notes(logging.Handler):
    """The library's notes (``logging`` under ``cylsfm``, level INFO and up) printed on the standard error
    stream of the moment, one line each."""

    def emit(self, record: logging.LogRecord) -> None:
        print(self.format(record), file=sys.stderr)


def _show_notes() -> None:
    """Route the library's notes to the terminal, once per process."""
    logger = logging.getLogger("cylsfm")
    if not any(isinstance(h, _Notes) for h in logger.handlers):
        logger.addHandler(_Notes())
        logger.setLevel(logging.INFO)


def main(argv: list[str] | None = None) -> int:
    """Run ``cylsfm ARGS``; returns the exit status (0, 2 for bad input, 130 when interrupted by Ctrl-C,
    143 by SIGTERM)."""
    _show_notes()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    try:
        with _sigterm_as_interrupt():
            return int(args._run(args) or 0)
    except CylsfmError as exc:
        print(f"cylsfm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        by = "SIGTERM" if isinstance(exc, Terminated) else "Ctrl-C"
        print(f"cylsfm {args.command}: interrupted by {by}; what was written is kept", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130
