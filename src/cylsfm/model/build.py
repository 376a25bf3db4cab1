"""The networks of a configuration: built fresh for training, or rebuilt from a checkpoint for inference."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..data.format import find_sequence_dirs
from ..errors import CylsfmError
from ..geometry import CylindricalCamera, load_camera
from ..nn import DispNet, PairPoseNet, PoseExpNet, PoseModel
from .checkpoint import CheckpointError, dataset_metadata, load_checkpoint, save_checkpoint
from .config import ConfigError, TrainConfig, config_from_dict, config_to_dict, preset

__all__ = [
    "DEFAULT_VFOV_H",
    "LoadedModels",
    "build_models",
    "load_models",
    "training_vfov_h",
    "untrained_checkpoint",
    "upgrade_pose_state",
]

#: Vertical half-extent ``vfov_h`` of the training panoramas when the training data does not say otherwise.
DEFAULT_VFOV_H = 1.0


def build_models(cfg: TrainConfig) -> tuple[DispNet, PoseModel]:
    """The networks of a configuration (freshly initialised): DispNet, and the pose model composed of the
    one-pass or the pair network with the head of ``cfg.pose_head`` and, on full panoramas, the compass."""
    n_src = cfg.data.seq_length - 1
    disp = DispNet(wrap=cfg.wrap)
    if cfg.model.antisymmetric:
        net: PoseExpNet | PairPoseNet = PairPoseNet(n_src, wrap=cfg.wrap, pose_head=cfg.pose_head)
    else:
        net = PoseExpNet(n_src, cfg.model.explainability, wrap=cfg.wrap, pose_head=cfg.pose_head)
    return disp, PoseModel(net, compass=cfg.model.compass and cfg.wrap)  # the compass reads full panoramas


def untrained_checkpoint(
    path: str | os.PathLike[str], width: int, height: int, fov: float = 360.0, recipe: str = "default"
) -> Path:
    """Write ``path``: a checkpoint of the preset ``recipe``'s networks, freshly initialised (seed 0), as if
    trained at ``width x height`` on ``fov``-degree crops (step 0; it loads like a trained one). For timing
    (the work does not depend on the weights) and tests. Returns ``path``."""
    cfg = preset(recipe)
    cfg.data.width, cfg.data.height, cfg.data.fov = width, height, fov
    torch.manual_seed(0)
    disp, pose = build_models(cfg)
    state = {
        "config": config_to_dict(cfg),
        "dataset": {"vfov_h": None},
        "step": 0,
        "disp_net": disp.state_dict(),
    }
    save_checkpoint(path, {**state, "pose_net": pose.state_dict()})
    return Path(path)


#: State-dict keys of the pose network before it was composed of parts -> today's (without the prefix of
#: the one-pass network inside the model: ``net.`` or, for the pair network, ``net.pair.``).
_OLD_POSE_KEYS = (
    (re.compile(r"^encoder\.(\d+)\.0\.(weight|bias)$"), r"encoder.convs.\1.\2"),
    (re.compile(r"^pose_pred\.(weight|bias)$"), r"head.conv.\1"),
    (re.compile(r"^upconvs\.(\d+)\.0\.(weight|bias)$"), r"explain.upconvs.\1.\2"),
    (re.compile(r"^mask_heads\.(\d+)\.(weight|bias)$"), r"explain.mask_heads.\1.\2"),
)


def upgrade_pose_state(
    state: dict[str, torch.Tensor], antisymmetric: bool
) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
    """A pose network's state dict in today's layout, and the training scaffold's slot prior it held.

    Checkpoints written before the pose network was composed of parts (one ``PoseExpNet`` class with
    keys ``encoder.N.0.*``, ``pose_pred.*``, ``upconvs.*``, ``mask_heads.*`` and the scaffold's
    ``slot_prior``) are mapped key by key; today's states are returned as they are.

    Args:
        state: the checkpoint's ``pose_net`` entry.
        antisymmetric: the run's ``model.antisymmetric`` (the pair network nests the one-pass one).

    Returns:
        ``(state, slot_prior)``: ``slot_prior`` ``[S,6]`` from an old training checkpoint, else ``None``.
    """
    if "pose_pred.weight" not in state:
        return state, None
    prefix = "net.pair." if antisymmetric else "net."
    out: dict[str, torch.Tensor] = {}
    prior = None
    for key, value in state.items():
        if key == "slot_prior":
            prior = value
            continue
        for pattern, new in _OLD_POSE_KEYS:
            if pattern.match(key):
                out[prefix + pattern.sub(new, key)] = value
                break
        else:
            out[key] = value  # unknown: the strict load names it
    return out, prior


def training_vfov_h(dataset: Mapping[str, Any], config: TrainConfig) -> float:
    """The vertical extent ``vfov_h`` (rows span ``h`` in ``[-vfov_h, vfov_h]``) of the panoramas a model was
    trained on.

    Recorded in the checkpoint's run metadata ``dataset`` when training starts; for checkpoints that hold
    none, read from the training dataset's ``camera.json`` (``height / (2 fy)``) when ``config.data.root``
    is still there and holds a cylindrical camera; otherwise :data:`DEFAULT_VFOV_H` (1.0, +-45 degrees: the
    cameras of ``cylsfm synth`` and of the paper's preparation).
    """
    recorded = dataset.get("vfov_h")
    if recorded:
        return float(recorded)
    root = getattr(getattr(config, "data", None), "root", "") or ""
    if root:
        try:
            cam = load_camera(find_sequence_dirs(root)[0] / "camera.json")
            if isinstance(cam, CylindricalCamera) and cam.wraps:
                return float(cam.height) / (2.0 * float(cam.fy))
        except (CylsfmError, OSError, IndexError):
            pass
    return DEFAULT_VFOV_H


@dataclass
class LoadedModels:
    """Networks restored from a checkpoint, in eval mode, with their configuration and the run metadata
    measured on their training data (``dataset``, see :mod:`cylsfm.model.checkpoint`)."""

    disp_net: DispNet
    pose_net: PoseModel
    config: TrainConfig
    step: int
    path: Path
    dataset: dict[str, Any] = field(default_factory=dict)

    @property
    def vfov_h(self) -> float:
        """The vertical extent of the training panoramas (:func:`training_vfov_h`)."""
        return training_vfov_h(self.dataset, self.config)


def load_models(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> LoadedModels:
    """Rebuild the networks of a checkpoint (or run directory) and load their weights.

    Checkpoints of earlier versions load through :func:`upgrade_pose_state`; a training scaffold they
    carry is not part of the inference networks and is dropped.

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
        pose.load_state_dict(upgrade_pose_state(state["pose_net"], cfg.model.antisymmetric)[0])
    except (RuntimeError, TypeError) as exc:
        raise CheckpointError(
            f"{p}: weights do not match the networks of its configuration ({exc})"
        ) from None
    disp.to(device).eval()
    pose.to(device).eval()
    return LoadedModels(disp, pose, cfg, int(state["step"]), p, dataset_metadata(state))
