"""Shared test fixtures."""

from __future__ import annotations

import os

import pytest
import torch
from hypothesis import settings

from cylsfm.data.synth.room import make_pose, render_room

__all__ = ["make_pose", "render_room"]

# Hypothesis: the same examples on every run and machine (a failure in CI is one that anybody can replay),
# drawn from a hash of each test, with no example database carried between runs and no deadline (the
# shared CI machines time examples too unevenly). HYPOTHESIS_PROFILE=explore draws new examples each run.
settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
settings.register_profile("explore", deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# Under pytest-xdist every worker gets its own core: more torch threads per worker only contend.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


@pytest.fixture
def room():
    """The room renderer: ``room(camera, c2w, supersample=3) -> (image, depth)``."""
    return render_room
