"""Checkpoints: atomic writes and safe loading (``weights_only=True``).

A checkpoint is a ``torch.save`` of a plain dict (tensors, numbers, strings, lists, dicts)::

    format        "cylsfm-checkpoint-v1"
    config        the resolved TrainConfig as a nested dict (what the user chose)
    dataset       run metadata, measured on the training data when the run started: {"vfov_h": rows of
                  the training panoramas span h in [-vfov_h, vfov_h], or None when they are not
                  cylindrical} (absent from checkpoints of earlier versions: dataset_metadata)
    step          optimisation steps done
    disp_net      DispNet state_dict
    pose_net      PoseExpNet state_dict
    optimizer     optimizer state_dict (training checkpoints)
    scaler        AMP grad-scaler state (or absent)
    rng           {"torch": ByteTensor, "numpy": [...], "python": [...], "cuda": [...]} (training checkpoints)

Wherever a checkpoint is asked for, a run directory also works: it means ``RUN/checkpoints/latest.pt``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from ..atomic import atomic_open
from ..errors import CylsfmError
from .config import config_metadata

__all__ = [
    "FORMAT",
    "CheckpointError",
    "checkpoint_id",
    "dataset_metadata",
    "load_checkpoint",
    "resolve_checkpoint",
    "save_checkpoint",
]

FORMAT = "cylsfm-checkpoint-v1"


class CheckpointError(CylsfmError):
    """A checkpoint file is missing, unreadable or not a cylsfm checkpoint."""


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """A checkpoint file, or a run directory meaning its latest checkpoint."""
    p = Path(path)
    if p.is_dir():
        for candidate in (p / "checkpoints" / "latest.pt", p / "latest.pt"):
            if candidate.is_file():
                return candidate
        raise CheckpointError(f"{p}: a run directory without checkpoints/latest.pt")
    if not p.exists():
        raise CheckpointError(f"{p}: checkpoint not found")
    return p


def checkpoint_id(checkpoint: str | os.PathLike[str]) -> str:
    """The checkpoint's resolved path, size and modification time: what a resumed output was computed
    with (a different file, or the same path trained further, is another checkpoint)."""
    p = Path(checkpoint).resolve()
    f = p / "checkpoints" / "latest.pt" if p.is_dir() else p
    stat = f.stat() if f.exists() else None
    return f"{p} {stat.st_size if stat else 0} {stat.st_mtime_ns if stat else 0}"


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> None:
    """Write ``state`` (see the module docstring) atomically: a temporary file, then ``os.replace``."""
    with atomic_open(path) as fh:
        torch.save({"format": FORMAT, **state}, fh)


def load_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint safely (``weights_only=True``: no code from the file is ever run)."""
    p = resolve_checkpoint(path)
    try:
        state = torch.load(p, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many kinds of errors for corrupt or hostile files
        raise CheckpointError(
            f"{p}: not a readable cylsfm checkpoint ({type(exc).__name__}: {exc})"
        ) from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{p}: not a cylsfm checkpoint (no format tag {FORMAT!r})")
    for key in ("config", "step", "disp_net", "pose_net"):
        if key not in state:
            raise CheckpointError(f"{p}: incomplete checkpoint, missing {key!r}")
    state["path"] = str(p)
    return state


def dataset_metadata(state: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's run metadata (``dataset``, see the module docstring); for a checkpoint of an earlier
    version, what its configuration recorded (:func:`~cylsfm.model.config.config_metadata`)."""
    recorded = state.get("dataset")
    if isinstance(recorded, dict):
        return dict(recorded)
    return config_metadata(state.get("config"))
