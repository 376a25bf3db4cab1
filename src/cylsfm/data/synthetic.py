"""Moved to :mod:`cylsfm.data.synth`; this name stays until every import uses the new one."""

from .synth import StreetScene, SynthConfig, generate_dataset, make_camera, render_frame  # noqa: F401
