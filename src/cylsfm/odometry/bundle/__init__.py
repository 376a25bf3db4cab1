"""The bundle adjustment of a ride (``cylsfm odometry --refine``: on by default; ``--no-bundle``): its
poses and sparse points adjusted together to the bearings of keypoints seen across many frames, seeded
and held by the odometry.

One module a job, in the order they run: :mod:`.features` (SIFT on every frame, across the seam, off the
mask), :mod:`.matching` (matches guided by the odometry's epipolar planes, tracks), :mod:`.adjust` (the
adjustment, GTSAM), :mod:`.stage` (the stage of the odometry's pipeline).
"""

from .adjust import Adjusted, BundleSettings, Observations, bundle_adjust, triangulate

__all__ = ["Adjusted", "BundleSettings", "Observations", "bundle_adjust", "triangulate"]
