"""Helpers shared by several test modules (importable: the tests folder is on the path)."""

from __future__ import annotations

from pathlib import Path

import torch

from cylsfm.model import build_models, save_checkpoint
from cylsfm.model.config import config_to_dict, preset


def untrained_checkpoint(directory: Path, width: int = 128, height: int = 32, fov: float = 360.0) -> Path:
    """``DIRECTORY/model.pt``: the default recipe untrained (seed 0), notionally trained at ``width x height``
    on ``fov``-degree crops."""
    cfg = preset("default")
    cfg.data.width, cfg.data.height, cfg.data.fov = width, height, fov
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    path = Path(directory) / "model.pt"
    state = {"config": config_to_dict(cfg), "step": 0, "disp_net": disp.state_dict()}
    save_checkpoint(path, {**state, "pose_net": pose.state_dict()})
    return path
