"""The bundle adjustment of a ride: its poses and sparse points adjusted together to the bearings of
keypoints seen across many frames, seeded and held by the odometry (:mod:`.adjust`)."""

from .adjust import Adjusted, BundleSettings, Observations, bundle_adjust, triangulate

__all__ = ["Adjusted", "BundleSettings", "Observations", "bundle_adjust", "triangulate"]
