"""Kept for compatibility: :class:`Predictor` lives in :mod:`cylsfm.model.predictor`."""

from .model.predictor import Predictor
from .runtime import pick_device

__all__ = ["Predictor", "pick_device"]
