"""Checkpoints: atomic writes, safe loading (``weights_only=True``), and rebuilding the networks.

A checkpoint is a ``torch.save`` of a plain dict (tensors, numbers, strings, lists, dicts)::

    format        "cylsfm-checkpoint-v1"
    config        the resolved TrainConfig as a nested dict
    step          optimisation steps done
    disp_net      DispNet state_dict
    pose_net      PoseExpNet state_dict
    optimizer     optimizer state_dict (training checkpoints)
    scaler        AMP grad-scaler state (or absent)
    rng           {"torch": ByteTensor, "numpy": [...], "python": [...], "cuda": [...]} (training checkpoints)
    sampler       {"epoch": int, "offset": int} position in the data order (training checkpoints)

Wherever a checkpoint is asked for, a run directory also works: it means ``RUN/checkpoints/latest.pt``.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..errors import CylsfmError
from ..nn import DispNet, PoseExpNet
from .config import ConfigError, TrainConfig, config_from_dict, config_to_dict

__all__ = [
    "FORMAT",
    "CheckpointError",
    "LoadedModels",
    "build_models",
    "load_checkpoint",
    "load_models",
    "resolve_checkpoint",
    "save_checkpoint",
]

FORMAT = "cylsfm-checkpoint-v1"


class CheckpointError(CylsfmError):
    """A checkpoint file is missing, unreadable or not a cylsfm checkpoint."""


def build_models(cfg: TrainConfig) -> tuple[DispNet, PoseExpNet]:
    """The networks of a configuration (freshly initialised)."""
    n_src = cfg.data.seq_length - 1
    disp = DispNet(wrap=cfg.wrap)
    pose = PoseExpNet(
        n_sources=n_src, explainability=cfg.model.explainability, wrap=cfg.wrap, pose_head=cfg.model.pose_head
    )
    return disp, pose


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


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> None:
    """Write ``state`` (see the module docstring) atomically: a temporary file, then ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"format": FORMAT, **state}
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        torch.save(state, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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


@dataclass
class LoadedModels:
    """Networks restored from a checkpoint, in eval mode, with their configuration."""

    disp_net: DispNet
    pose_net: PoseExpNet
    config: TrainConfig
    step: int
    path: Path


def load_models(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> LoadedModels:
    """Rebuild the networks of a checkpoint (or run directory) and load their weights."""
    state = load_checkpoint(path, map_location=device)
    p = Path(state["path"])
    try:
        cfg = config_from_dict(state["config"], where=f"{p} (config)")
    except ConfigError as exc:
        raise CheckpointError(str(exc)) from None
    disp, pose = build_models(cfg)
    try:
        disp.load_state_dict(state["disp_net"])
        pose.load_state_dict(state["pose_net"])
    except (RuntimeError, TypeError) as exc:
        raise CheckpointError(
            f"{p}: weights do not match the networks of its configuration ({exc})"
        ) from None
    disp.to(device).eval()
    pose.to(device).eval()
    return LoadedModels(disp, pose, cfg, int(state["step"]), p)


def config_state(cfg: TrainConfig) -> dict[str, Any]:
    """The configuration as stored in checkpoints."""
    return config_to_dict(cfg)
