"""How loops are looked for and accepted: :class:`LoopSettings`, checked where it is made."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ...errors import InputError
from ...geometry.align import AlignConfig

__all__ = ["LoopSettings"]


@dataclass(frozen=True)
class LoopSettings:
    """How loops are looked for and accepted.

    Attributes:
        min_gap: the two frames of a loop are at least this many frames apart.
        window: sequence matching over ``2 * window + 1`` frames around each.
        per_query: the nearest earlier frames each query frame keeps (apart by at least ``window``).
        max_pairs: pairs verified at most in a ride.
        min_inliers: the smallest inlier fraction (both ways, :func:`~cylsfm.geometry.photometric.photometric_inliers`)
            of an accepted loop seen in much the same direction (a texture seen again at the same scale).
        turned_deg, min_inliers_turned: a revisit whose yaw is more than ``turned_deg`` degrees sees each
            texture from elsewhere (a street driven back on the other side of the road): its inliers are
            counted insensitive to sampling within a pixel, and at least ``min_inliers_turned`` must fit.
        max_rotation_deg, max_translation: the largest disagreement of the two directions' poses:
            rotation (degrees) and translation (as a fraction of the first frame's median depth).
        max_drift: a loop may move the second frame, relative to the first, by at most this fraction of
            the distance the odometry travelled between them (plus a tenth of the median depth): the
            drift odometry can plausibly have; a loop that asks for more is a place that only looks alike.
        yaw_drift_deg, yaw_drift_per_frame_deg, yaw_drift_max_deg: the heading the odometry can plausibly
            have lost between the two frames: ``yaw_drift_deg`` plus ``yaw_drift_per_frame_deg`` per frame
            between them, at most ``yaw_drift_max_deg`` (degrees; below 90, so that a street seen the
            other way round is never taken for the same view). The visual compass looks for the yaw only
            that close to the odometry's, and a loop that turns farther from it is rejected: a straight
            street looks much the same ahead and behind, and a crossing four ways round, but the odometry
            knows which way the camera faces.
        support: an accepted loop needs at least this many verified loops (itself included) nearby (both
            frames within ``span`` frames of its own) that agree with it through the odometry between
            them; a revisit is seen by several consecutive frames, a lookalike rarely agrees with itself.
            The others may be accepted loops or pairs seen the same way round that fit less well (at
            least ``min_inliers_support`` of their pixels, within the odometry's drift) but whose own
            alignment found the pose the loop predicts: a ride that ends where it started sees its start
            only from its last few frames, each a little farther back than the last.
        min_inliers_support: see ``support``.
        span: frames; see ``support``.
        align: the alignment's settings.
    """

    min_gap: int = 50
    window: int = 5
    per_query: int = 2
    max_pairs: int = 64
    min_inliers: float = 0.5
    turned_deg: float = 90.0
    min_inliers_turned: float = 0.6
    max_rotation_deg: float = 3.0
    max_translation: float = 0.1
    max_drift: float = 0.15
    yaw_drift_deg: float = 30.0
    yaw_drift_per_frame_deg: float = 0.1
    yaw_drift_max_deg: float = 80.0
    support: int = 2
    min_inliers_support: float = 0.3
    span: int = 20
    align: AlignConfig = field(default_factory=lambda: AlignConfig(levels=4, iterations=8))

    def __post_init__(self) -> None:
        if self.min_gap < 2 or self.window < 0 or self.per_query < 1 or self.max_pairs < 0:
            raise InputError(
                "loops: min_gap must be at least 2, window at least 0, per_query at least 1, max_pairs at "
                f"least 0; got {self.min_gap}, {self.window}, {self.per_query}, {self.max_pairs}"
            )
        if (
            self.yaw_drift_deg < 0
            or self.yaw_drift_per_frame_deg < 0
            or not 0 <= self.yaw_drift_max_deg <= 180
        ):
            raise InputError(
                "loops: yaw_drift_deg and yaw_drift_per_frame_deg must be >= 0 and yaw_drift_max_deg in "
                f"[0, 180], got {self.yaw_drift_deg}, {self.yaw_drift_per_frame_deg}, {self.yaw_drift_max_deg}"
            )
        fractions = (self.min_inliers, self.min_inliers_turned, self.min_inliers_support)
        if not all(0 <= f <= 1 for f in fractions):
            raise InputError(
                "loops: min_inliers, min_inliers_turned and min_inliers_support must be in [0, 1], got "
                + ", ".join(f"{f:g}" for f in fractions)
            )

    def yaw_allowance(self, i: int, j: int) -> float:
        """The heading drift (radians) the odometry can plausibly have between frames ``i`` and ``j``."""
        drift = self.yaw_drift_deg + self.yaw_drift_per_frame_deg * abs(j - i)
        return math.radians(min(self.yaw_drift_max_deg, drift))
