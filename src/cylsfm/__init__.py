"""cylsfm: self-supervised depth and ego-motion from 360-degree cylindrical panoramic video.

The public library API: camera models and view synthesis. Networks live in :mod:`cylsfm.nn`, losses in
:mod:`cylsfm.losses`, whole-ride trajectories in :mod:`cylsfm.odometry` (``import cylsfm.odometry``; the
module is callable).
"""

from ._version import __version__
from .geometry import CylindricalCamera, PinholeCamera, inverse_warp

__all__ = ["CylindricalCamera", "PinholeCamera", "__version__", "inverse_warp"]
