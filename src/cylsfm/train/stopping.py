"""When training stops: the budget, a signal (Ctrl-C, a scheduler's SIGTERM) or a non-finite loss, agreed
by every process of a data-parallel run.

Each process judges the stop conditions on its own (its clock, the signals it received, its loss); at each
step boundary the processes exchange their verdicts (one small all-reduce, taking the most severe), so that
all of them stop at the same step and none waits forever in a gradient all-reduce that the others left.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

import torch
import torch.distributed as dist

__all__ = ["CONTINUE", "NON_FINITE", "OUT_OF_TIME", "SIGNALLED", "StopRequests", "agree"]

#: Verdicts, by severity (the agreed verdict is the largest).
CONTINUE, OUT_OF_TIME, SIGNALLED, NON_FINITE = 0, 1, 2, 3


class StopRequests:
    """The signals received while training: SIGINT and SIGTERM set :attr:`signal` (its name) instead of
    interrupting the step; a second SIGINT interrupts at once (``KeyboardInterrupt``)."""

    def __init__(self) -> None:
        self.signal: str | None = None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signal.Signals(signum).name

    @contextmanager
    def installed(self) -> Iterator[StopRequests]:
        """Catch the signals within the block (only in the main thread, where Python delivers them)."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield self
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)


def agree(verdict: int, world: int, device: torch.device) -> int:
    """The most severe of every process's ``verdict`` (this process's own when it trains alone)."""
    if world <= 1:
        return verdict
    t = torch.tensor([verdict], dtype=torch.int64, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return int(t.item())
