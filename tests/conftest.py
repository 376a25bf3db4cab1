"""Shared test fixtures."""

from __future__ import annotations

import os

import pytest
import torch

from cylsfm.data.synth.room import make_pose, render_room

__all__ = ["make_pose", "render_room"]

# Under pytest-xdist every worker gets its own core: more torch threads per worker only contend.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


@pytest.fixture
def room():
    """The room renderer: ``room(camera, c2w, supersample=3) -> (image, depth)``."""
    return render_room
