"""Fixtures shared by the odometry tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from helpers import untrained_checkpoint


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    """An untrained checkpoint of the default recipe at 128x32 (its poses are noise: refinement must work)."""
    return untrained_checkpoint(tmp_path_factory.mktemp("ckpt"))
