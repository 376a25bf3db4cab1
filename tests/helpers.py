"""Helpers shared by several test modules (importable: the tests folder is on the path)."""

from __future__ import annotations

import errno
from pathlib import Path

import torch

from cylsfm.model import preset
from cylsfm.model import untrained_checkpoint as model_untrained


def untrained_checkpoint(directory: Path, width: int = 128, height: int = 32, fov: float = 360.0) -> Path:
    """``DIRECTORY/model.pt``: the default recipe untrained (seed 0), notionally trained at ``width x height``
    on ``fov``-degree crops (:func:`cylsfm.model.untrained_checkpoint`)."""
    return model_untrained(Path(directory) / "model.pt", width, height, fov)


def failing_writes(monkeypatch, pattern: str, error: int) -> None:
    """From now on, atomic writes (:func:`cylsfm.atomic.atomic_open`) of files whose name matches the glob
    ``pattern`` fail as on a full disk (``errno.ENOSPC``: the first write raises) or a read-only directory
    (``errno.EROFS``: the temporary file cannot be created)."""
    import fnmatch
    import os
    import tempfile

    real_mkstemp, real_fdopen, doomed = tempfile.mkstemp, os.fdopen, set()

    class _Full:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.fh.__exit__(*exc)

        def write(self, data):
            raise OSError(error, os.strerror(error))

        def __getattr__(self, name):
            return getattr(self.fh, name)

    def mkstemp(*args, prefix="", **kwargs):
        if fnmatch.fnmatch(prefix[1:-1], pattern):
            if error != errno.ENOSPC:
                raise OSError(error, os.strerror(error))
            fd, tmp = real_mkstemp(*args, prefix=prefix, **kwargs)
            doomed.add(fd)
            return fd, tmp
        return real_mkstemp(*args, prefix=prefix, **kwargs)

    def fdopen(fd, *args, **kwargs):
        fh = real_fdopen(fd, *args, **kwargs)
        if fd in doomed:  # (forget the number: once closed, another thread's file may get it)
            doomed.discard(fd)
            return _Full(fh)
        return fh

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(os, "fdopen", fdopen)


def tiny_training_config(root, **extra):
    """The default recipe on the tiny data of ``tests/train`` (128x32, batch 2, every step logged and
    checkpointed in ``latest.pt``); ``extra``: more ``key=value`` overrides."""
    from cylsfm.model.config import apply_overrides

    items = [
        f"data.root='{root}'",
        "data.width=128",
        "data.height=32",
        "data.split=null",
        "data.workers=0",
        "batch_size=2",
        "log_every=1",
        "image_every=2",
        "latest_every=1",
        "checkpoint_every=0",
    ] + [f"{k}={v}" for k, v in extra.items()]
    return apply_overrides(preset("default"), items)


class PoseStub(torch.nn.Module):
    """A stand-in pose network for :class:`~cylsfm.model.Predictor`: what it reads of a
    :class:`~cylsfm.nn.PoseModel` (``pairs``, ``n_sources``, the network ``net`` with ``pair_vectors`` and
    ``with_compass``), without a compass.
    Subclasses define ``forward(target, sources) -> (pose [B,S,6], None)``."""

    pairs = True
    n_sources = 2

    @property
    def net(self) -> torch.nn.Module:
        return self

    def pair_vectors(self, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        """As :meth:`~cylsfm.nn.PairPoseNet.pair_vectors`: ``forward`` on each pair as a window of one source."""
        return self.forward(first, second[:, None])[0][:, 0]

    compass = None

    def with_compass(
        self, pose: torch.Tensor, target: torch.Tensor, sources: torch.Tensor, yaws=None
    ) -> torch.Tensor:
        return pose
