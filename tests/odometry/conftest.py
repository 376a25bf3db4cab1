"""Fixtures shared by the odometry tests."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cylsfm.model import build_models, save_checkpoint
from cylsfm.model.config import config_to_dict, preset


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    """An untrained checkpoint of the default recipe at 128x32 (its poses are noise: refinement must work)."""
    cfg = preset("default")
    cfg.data.width, cfg.data.height = 128, 32
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    state = {
        "config": config_to_dict(cfg),
        "step": 0,
        "disp_net": disp.state_dict(),
        "pose_net": pose.state_dict(),
    }
    save_checkpoint(path, state)
    return path
