"""A trained model: its typed configuration and presets, checkpoints, building and loading the networks,
and :class:`Predictor`, which runs them on images of any size."""

from .build import LoadedModels, build_models, load_models, untrained_checkpoint
from .checkpoint import CheckpointError, load_checkpoint, resolve_checkpoint, save_checkpoint
from .config import ConfigError, TrainConfig, apply_overrides, config_from_dict, config_to_dict, preset
from .predictor import Predictor

__all__ = [
    "CheckpointError",
    "ConfigError",
    "LoadedModels",
    "Predictor",
    "TrainConfig",
    "apply_overrides",
    "build_models",
    "config_from_dict",
    "config_to_dict",
    "load_checkpoint",
    "load_models",
    "preset",
    "resolve_checkpoint",
    "save_checkpoint",
    "untrained_checkpoint",
]
