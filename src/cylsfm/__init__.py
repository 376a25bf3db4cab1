"""cylsfm: self-supervised depth and ego-motion from 360-degree cylindrical panoramic video.

The public library API: camera models and view synthesis, and :mod:`cylsfm.odometry` (callable: a ride's
trajectory), imported when first used. Networks live in :mod:`cylsfm.nn`, losses in :mod:`cylsfm.losses`.
"""

__version__ = "0.1.0"

from .geometry import CylindricalCamera, PinholeCamera, inverse_warp

__all__ = ["CylindricalCamera", "PinholeCamera", "__version__", "inverse_warp"]


def __getattr__(name: str):
    """``cylsfm.odometry``, imported on first use (it loads the networks' code)."""
    if name == "odometry":
        import importlib

        return importlib.import_module(".odometry", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
