"""Preparing footage as dataset format v1 (``cylsfm prepare``): one sequence per input, written frame by
frame, resumable and idempotent.

:mod:`~cylsfm.data.prepare.sequence` is the resumable sequence writer every preparation uses;
:mod:`~cylsfm.data.prepare.equirect` converts equirectangular 360-degree videos and image folders (the
output of consumer 360 cameras) and folders of ready cylindrical panoramas.
"""

from __future__ import annotations

from .equirect import EquirectOptions, prepare_equirect, prepare_frames
from .sequence import PreparedSequence

__all__ = ["EquirectOptions", "PreparedSequence", "prepare_equirect", "prepare_frames"]
