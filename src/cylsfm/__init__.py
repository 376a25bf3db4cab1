"""cylsfm: self-supervised depth and ego-motion from 360-degree cylindrical panoramic video.

The public library API: camera models and view synthesis. Networks live in :mod:`cylsfm.nn`, losses in
:mod:`cylsfm.losses`.
"""

__version__ = "0.1.0"

from .geometry import CylindricalCamera, PinholeCamera, inverse_warp

__all__ = ["CylindricalCamera", "PinholeCamera", "__version__", "inverse_warp"]
