"""Preparing footage as dataset format v1 (``cylsfm prepare``): one sequence per input, written frame by
frame, resumable and idempotent.

:mod:`~cylsfm.data.prepare.sequence` is the resumable sequence writer every preparation uses;
:mod:`~cylsfm.data.prepare.equirect` converts equirectangular 360-degree videos and image folders (the
output of consumer 360 cameras) and folders of ready cylindrical panoramas; :mod:`~cylsfm.data.prepare.headcam` the paper's Headcam videos as it prepared them;
:mod:`~cylsfm.data.prepare.rig` stitches pinhole views sharing a centre (``prepare views``) and
:mod:`~cylsfm.data.prepare.synthia` SYNTHIA-Seqs' four views a frame, with depth and poses.
"""

from __future__ import annotations

from .equirect import EquirectOptions, prepare_equirect, prepare_frames
from .headcam import prepare_headcam
from .rig import RigOptions, prepare_views
from .sequence import PreparedSequence
from .synthia import SynthiaOptions, prepare_synthia

__all__ = [
    "EquirectOptions",
    "PreparedSequence",
    "RigOptions",
    "SynthiaOptions",
    "prepare_equirect",
    "prepare_frames",
    "prepare_headcam",
    "prepare_synthia",
    "prepare_views",
]
