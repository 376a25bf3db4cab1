"""The networks of a configuration: built fresh for training, or rebuilt from a checkpoint for inference."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from ..nn import DispNet, PoseExpNet
from .checkpoint import CheckpointError, load_checkpoint
from .config import ConfigError, TrainConfig, config_from_dict

__all__ = ["LoadedModels", "build_models", "load_models"]


def build_models(cfg: TrainConfig) -> tuple[DispNet, PoseExpNet]:
    """The networks of a configuration (freshly initialised)."""
    n_src = cfg.data.seq_length - 1
    disp = DispNet(wrap=cfg.wrap)
    pose = PoseExpNet(
        n_sources=n_src,
        explainability=cfg.model.explainability,
        wrap=cfg.wrap,
        pose_head=cfg.pose_head,  # "auto" resolved by the field of view
        compass=cfg.model.compass and cfg.wrap,  # the compass reads full panoramas only
        antisymmetric=cfg.model.antisymmetric,
        slot_prior=cfg.model.scaffold,
        pose_level=cfg.model.pose_level,
        antipodal=cfg.model.pose_antipodal,
    )
    return disp, pose


@dataclass
class LoadedModels:
    """Networks restored from a checkpoint, in eval mode, with their configuration."""

    disp_net: DispNet
    pose_net: PoseExpNet
    config: TrainConfig
    step: int
    path: Path


def load_models(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> LoadedModels:
    """Rebuild the networks of a checkpoint (or run directory) and load their weights.

    Raises:
        CheckpointError: the file is missing, not a cylsfm checkpoint, or its weights do not fit the
            networks of its own configuration.
    """
    state = load_checkpoint(path, map_location=device)
    p = Path(state["path"])
    try:
        cfg = config_from_dict(state["config"], where=f"{p} (config)", saved=True)
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
