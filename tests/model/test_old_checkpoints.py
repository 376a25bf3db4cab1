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

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from cylsfm.model import build_models, load_models, save_checkpoint, untrained_checkpoint
from cylsfm.model.checkpoint import CheckpointError
from cylsfm.model.config import DataConfig, config_from_dict, config_to_dict, preset
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


def _untrained(path: Path, root: str = "", dataset: dict | None = None, vfov_h: float | None = None) -> Path:
    """A checkpoint of fresh networks at 64x16; ``vfov_h`` recorded in its configuration as earlier versions
    did, ``dataset`` as its run metadata (none: a checkpoint of an earlier version)."""
    cfg = preset("default")
    cfg.data.width, cfg.data.height, cfg.data.root = 64, 16, root
    disp, pose = build_models(cfg)
    config = config_to_dict(cfg)
    if vfov_h is not None:
        config["data"]["vfov_h"] = vfov_h
    state = {"config": config, "step": 0, "disp_net": disp.state_dict(), "pose_net": pose.state_dict()}
    save_checkpoint(path, state | ({"dataset": dataset} if dataset is not None else {}))
    return path


def test_the_training_panoramas_extent_is_run_metadata(tmp_path: Path) -> None:
    """``vfov_h`` is measured on the training data and kept beside the configuration; a checkpoint of an
    earlier version that recorded it in its configuration (``data.vfov_h``) loads with it as metadata."""
    from cylsfm.model import Predictor
    from cylsfm.model.plan import model_camera, model_vfov_h

    fields = {f.name for f in dataclasses.fields(DataConfig)}
    assert "vfov_h" not in fields  # not a setting
    assert config_from_dict({"data": {"vfov_h": 0.5}}, saved=True) == config_from_dict({}, saved=True)
    for name, kwargs in {"metadata": {"dataset": {"vfov_h": 0.6}}, "earlier": {"vfov_h": 0.6}}.items():
        models = load_models(_untrained(tmp_path / f"{name}.pt", **kwargs))
        assert models.dataset == {"vfov_h": 0.6} and models.vfov_h == 0.6
        predictor = Predictor(models)
        assert predictor.vfov_h == model_vfov_h(predictor) == model_vfov_h(models) == 0.6
        assert float(model_camera(predictor).fy) == pytest.approx(16 / (2 * 0.6))


def test_without_a_measurement_the_extent_falls_back_to_the_dataset_then_to_one(tmp_path: Path) -> None:
    """Checkpoints that record no ``vfov_h``: the training dataset's camera while it is there, else 1; the
    earlier call form ``model_vfov_h(predictor.config)`` gives these fallbacks."""
    from cylsfm.data import SequenceWriter
    from cylsfm.geometry import CylindricalCamera
    from cylsfm.model import Predictor
    from cylsfm.model.plan import DEFAULT_VFOV_H, model_vfov_h

    writer = SequenceWriter(tmp_path / "data" / "seq", CylindricalCamera.full(64, 16, 0.8))
    writer.add_frame(torch.zeros(16, 64, 3, dtype=torch.uint8).numpy())
    writer.finish()
    with_data = Predictor(load_models(_untrained(tmp_path / "a.pt", root=str(tmp_path / "data"))))
    assert with_data.vfov_h == pytest.approx(0.8) and model_vfov_h(with_data.config) == pytest.approx(0.8)
    gone = Predictor(load_models(_untrained(tmp_path / "b.pt", root=str(tmp_path / "gone"))))
    assert gone.vfov_h == model_vfov_h(gone.config) == DEFAULT_VFOV_H == 1.0
    untrained = Predictor(load_models(untrained_checkpoint(tmp_path / "c.pt", 64, 16)))
    assert untrained.models.dataset == {"vfov_h": None} and untrained.vfov_h == 1.0
