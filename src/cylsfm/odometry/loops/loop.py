"""A verified pair of frames at the same place (:class:`Loop`) and why it was or was not accepted
(:class:`Reason`, a code: the words for people are its :attr:`Reason.message`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from ...evaluate.motion import yaw_angle
from ...geometry import invert

__all__ = ["Loop", "Reason", "odometry_yaw", "rotation_deg"]


class Reason(str, Enum):
    """Why a verified pair was accepted or not, as the stages of loop closure decide it."""

    ACCEPTED = "accepted"
    #: too few pixels fit one way or the other (:func:`~cylsfm.odometry.loops.verify.verify_loops`)
    FEW_INLIERS = "few_inliers"
    #: the alignments both ways do not compose to the identity
    DISAGREE = "directions_disagree"
    #: the loop moves the second frame farther than the odometry can plausibly have drifted
    BEYOND_DRIFT = "beyond_drift"
    #: the loop turns the second frame farther than the odometry's heading can have drifted
    TURNED_BEYOND_DRIFT = "turned_beyond_drift"
    #: no other loop nearby agrees with it through the odometry
    UNSUPPORTED = "unsupported"

    @property
    def message(self) -> str:
        """The reason in words (``""`` when accepted)."""
        return _MESSAGES[self]


_MESSAGES = {
    Reason.ACCEPTED: "",
    Reason.FEW_INLIERS: "few inliers",
    Reason.DISAGREE: "the two ways disagree",
    Reason.BEYOND_DRIFT: "farther than the odometry's drift",
    Reason.TURNED_BEYOND_DRIFT: "turned farther than the odometry's drift",
    Reason.UNSUPPORTED: "no other loop agrees",
}


@dataclass(frozen=True)
class Loop:
    """A verified pair of frames ``i < j`` at the same place.

    Attributes:
        i, j: the frames.
        pose: ``T_{i->j}`` ``[4,4]`` (float64, ``p_j = T p_i``), translation in frame ``i``'s depth unit.
        ratio: frame ``j``'s depth unit per frame ``i``'s (the scale between the two).
        inliers: the smaller of the two directions' inlier fractions.
        disagreement: ``(degrees, fraction of the median depth)`` between the two directions (``nan``:
            the way back was not aligned).
        distance: the sequence-matched descriptor distance relative to the query's median.
        reason: whether it was accepted, and if not, which check it failed.
    """

    i: int
    j: int
    pose: np.ndarray
    ratio: float
    inliers: float
    disagreement: tuple[float, float]
    distance: float
    reason: Reason = Reason.ACCEPTED

    @property
    def accepted(self) -> bool:
        """Whether it passed the verification and the checks against the odometry."""
        return self.reason is Reason.ACCEPTED

    @property
    def yaw_deg(self) -> float:
        """The yaw of :attr:`pose` in degrees."""
        return math.degrees(float(yaw_angle(self.pose)))


def odometry_yaw(c2w: np.ndarray, i: int, j: int) -> float:
    """The yaw (radians) of the odometry's ``T_{i->j}`` from camera-to-world poses ``[M,4,4]`` (as
    :func:`~cylsfm.geometry.compass_yaw`'s)."""
    return float(yaw_angle(invert(c2w[j]) @ c2w[i]))


def rotation_deg(r: np.ndarray) -> float:
    """The angle (degrees) of a rotation matrix ``[3,3]``."""
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1) / 2))))
