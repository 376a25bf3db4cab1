"""Checkpoints and configurations written before the pose network was composed of parts still load, and
their networks give the same outputs.

``data/pre_parts_pose_networks.json`` was recorded with the code of commit 94a2060 (the one-class
``PoseExpNet``): for four configurations (the default recipe's pair network with the compass, the paper's
network with explainability masks, the improved recipe's one-pass network, and the default recipe on a
180-degree crop, without wrap-around) it holds the saved configuration, the pose network's state-dict keys
and shapes, and the poses (and mask means) that network gave with weights drawn from ``torch.randn`` seeded
by ``1000 + i`` for the ``i``-th key, times 0.05, on inputs drawn from ``torch.rand`` seeded by 7.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from cylsfm.model import load_models, save_checkpoint
from cylsfm.model.checkpoint import CheckpointError
from cylsfm.model.config import config_from_dict, preset
from cylsfm.nn import DispNet

FIXTURE = json.loads((Path(__file__).parent / "data" / "pre_parts_pose_networks.json").read_text())


def _old_weights(keys: list) -> dict[str, torch.Tensor]:
    out = {}
    for i, (key, shape) in enumerate(keys):
        g = torch.Generator().manual_seed(FIXTURE["weights_seed_base"] + i)
        out[key] = (torch.randn(shape, generator=g, dtype=torch.float64) * 0.05).float()
    return out


def _old_checkpoint(path: Path, case: dict) -> Path:
    cfg = config_from_dict(case["config"], saved=True)
    save_checkpoint(
        path,
        {
            "config": case["config"],
            "step": 7,
            "disp_net": DispNet(wrap=cfg.wrap).state_dict(),
            "pose_net": _old_weights(case["keys"]),
        },
    )
    return path


@pytest.mark.parametrize("name", sorted(FIXTURE["cases"]))
def test_old_checkpoints_load_and_give_the_same_poses(tmp_path: Path, name: str) -> None:
    case = FIXTURE["cases"][name]
    models = load_models(_old_checkpoint(tmp_path / f"{name}.pt", case))
    assert "slot_prior" not in str(list(models.pose_net.state_dict()))  # the scaffold stays behind
    g = torch.Generator().manual_seed(FIXTURE["inputs_seed"])
    target = torch.rand(2, 3, 64, 256, generator=g)
    sources = torch.rand(2, 2, 3, 64, 256, generator=g)
    if models.config.data.fov < 360:
        target, sources = target[..., 64:192], sources[..., 64:192]
    with torch.no_grad():
        pose, masks = models.pose_net(target, sources)
    torch.testing.assert_close(pose, torch.tensor(case["pose"]), rtol=1e-5, atol=1e-7)
    if case["mask_means"] is None:
        assert masks is None
    else:
        assert [float(m.double().mean()) for m in masks] == pytest.approx(case["mask_means"], rel=1e-6)


def test_an_old_training_checkpoint_resumes_with_its_scaffold(tmp_path: Path) -> None:
    """The slot prior that an old checkpoint kept inside the pose network moves to the trainer's scaffold."""
    from cylsfm.model.build import upgrade_pose_state

    case = FIXTURE["cases"]["default"]
    old = _old_weights(case["keys"])
    assert "slot_prior" in old
    state, prior = upgrade_pose_state(old, antisymmetric=True)
    assert prior is old["slot_prior"] and all(k.startswith("net.pair.") for k in state)
    assert upgrade_pose_state(state, antisymmetric=True) == (state, None)  # today's layout: unchanged


def test_old_configurations_load_and_removed_options_are_named(tmp_path: Path) -> None:
    saved = FIXTURE["cases"]["default"]["config"]
    assert "mirror_exact" in saved["data"] and "pose_level" in saved["model"]  # written by the old code
    cfg = config_from_dict(saved, saved=True)
    assert cfg.model.antisymmetric and cfg.model.compass
    on = json.loads(json.dumps(saved))
    on["data"]["roll"] = True
    with pytest.raises(Exception, match=r"data\.roll=True .*rejected options"):
        config_from_dict(on, saved=True)
    bad = tmp_path / "bad.pt"
    save_checkpoint(bad, {"config": on, "step": 1, "disp_net": {}, "pose_net": {}})
    with pytest.raises(CheckpointError, match=r"data\.roll"):
        load_models(bad)
    assert config_from_dict({"preset": "default", "plain_photometric_steps": 0}).model.compass
    assert preset("default").model.antisymmetric
