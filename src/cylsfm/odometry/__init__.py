"""Whole-ride trajectories from panoramic video: ``cylsfm odometry`` and ``cylsfm.odometry(...)``.

For a video, a folder of frames or a dataset sequence, :func:`odometry`:

1. brings every frame to the model's cylinder at the network's size (equirectangular or other cameras are
   resampled as for ``cylsfm predict``), predicts its depth, and runs the pose network over every window
   of ``seq_length`` frames; each consecutive step ``T_{j->j+1}`` comes from the window centred on ``j``;
2. with ``refine``, refines each step by direct photometric alignment of frame ``j+1`` against frame ``j``
   with frame ``j``'s depth (:mod:`~cylsfm.geometry.align`: wrap-aware, coarse to fine, robust,
   Levenberg-Marquardt), starting from the network's step, or from the visual compass's yaw with the
   network's translation where that aligns better;
3. chains the steps into camera-to-world poses and writes them.

Scale: network units, or metres when the camera's height above the ground is given (the ground fitted
below the horizon in every frame's depth, :mod:`~cylsfm.geometry.ground`), or metres when the refinement
uses ground-truth depth (``depth_from``). The trajectory file's header says which.

Files in ``OUT``::

    trajectory.txt           TUM: t tx ty tz qx qy qz qw (camera-to-world), unit in the header
    trajectory_network.txt   with refine: the pose network's own steps chained
    trajectory.png           top view (Sim(3)-aligned to the ground truth with the references, when known)
    metrics.json             with ground truth (a dataset sequence with poses.txt): evo's APE (Sim(3)) and
                             RPE, per-step rotation and direction errors, for the trajectory, the network,
                             the visual compass, constant velocity and zero motion
    odometry.json            frames, unit, scale, seconds and where they went
    depth/FRAME.npy          with depth maps asked for: each frame's depth (the view the network sees)
    .odometry-state.npz      progress: a killed run given the same arguments continues from it

The module is callable: ``cylsfm.odometry(INPUT, CHECKPOINT, OUT, OdometrySettings(refine=True))`` is
:func:`odometry`.
"""

import sys
import types

from ..geometry.align import AlignConfig, AlignResult, align
from ..geometry.ground import ground_height, metric_scale
from .exports import export_colmap, export_rerun
from .frames import Ride, open_ride
from .run import OdometryResult, odometry
from .settings import OdometrySettings

__all__ = [
    "AlignConfig",
    "AlignResult",
    "OdometryResult",
    "OdometrySettings",
    "Ride",
    "align",
    "export_colmap",
    "export_rerun",
    "ground_height",
    "metric_scale",
    "odometry",
    "open_ride",
]


class _CallableModule(types.ModuleType):
    """This package, callable as :func:`odometry`."""

    def __call__(self, *args, **kwargs) -> OdometryResult:
        return odometry(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
