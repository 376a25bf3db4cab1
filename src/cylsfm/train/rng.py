"""Random-number states of torch, NumPy and Python as plain data, for checkpoints loaded with
``weights_only=True`` (no pickled objects)."""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["restore_rng", "rng_state"]


def rng_state() -> dict[str, Any]:
    """Every generator's state: ``{"torch", "numpy", "python"[, "cuda"]}`` of tensors, numbers and lists."""
    rng = {
        "torch": torch.get_rng_state(),
        "numpy": _numpy_state_to_list(np.random.get_state()),  # noqa: NPY002 - the global state is what we save
        "python": _python_state_to_list(random.getstate()),
    }
    if torch.cuda.is_available():
        rng["cuda"] = torch.cuda.get_rng_state_all()
    return rng


def restore_rng(rng: dict[str, Any]) -> None:
    """Restore the states saved by :func:`rng_state` (missing entries are left alone)."""
    if "torch" in rng:
        torch.set_rng_state(rng["torch"])
    if "numpy" in rng:
        np.random.set_state(_numpy_state_from_list(rng["numpy"]))  # noqa: NPY002
    if "python" in rng:
        random.setstate(_python_state_from_list(rng["python"]))
    if "cuda" in rng and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(rng["cuda"])


def _numpy_state_to_list(state: tuple) -> list:
    name, keys, pos, has_gauss, cached = state
    return [name, torch.from_numpy(np.asarray(keys, dtype=np.int64)), int(pos), int(has_gauss), float(cached)]


def _numpy_state_from_list(data: list) -> tuple:
    name, keys, pos, has_gauss, cached = data
    return (
        name,
        np.asarray(keys.numpy() if isinstance(keys, Tensor) else keys, dtype=np.uint32),
        pos,
        has_gauss,
        cached,
    )


def _python_state_to_list(state: tuple) -> list:
    version, internal, gauss = state
    return [version, list(internal), gauss]


def _python_state_from_list(data: list) -> tuple:
    version, internal, gauss = data
    return (version, tuple(internal), gauss)
