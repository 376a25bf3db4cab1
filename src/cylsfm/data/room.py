"""Moved to :mod:`cylsfm.data.synth.room`; this name stays until every import uses the new one."""

from .synth.room import PILLAR_HI, PILLAR_LO, ROOM_HI, ROOM_LO, make_pose, render_room  # noqa: F401
