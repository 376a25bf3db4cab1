"""The benchmarks' model: the default recipe's networks at a given size, untrained (seeded), saved as a
checkpoint. Timing does not depend on the weights."""

from __future__ import annotations

from pathlib import Path

import torch

from cylsfm.model import build_models, preset, save_checkpoint
from cylsfm.model.config import config_to_dict


def untrained_checkpoint(path: Path, width: int, height: int) -> Path:
    """Write ``path``: the default recipe at ``width x height``, untrained (seed 0); returns ``path``."""
    cfg = preset("default")
    cfg.data.width, cfg.data.height = width, height
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    state = {"config": config_to_dict(cfg), "step": 0, "disp_net": disp.state_dict()}
    save_checkpoint(path, {**state, "pose_net": pose.state_dict()})
    return path
