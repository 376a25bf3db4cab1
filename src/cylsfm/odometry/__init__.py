"""Whole-ride trajectories from panoramic video: ``cylsfm odometry`` and ``cylsfm.odometry(...)``.

For a video, a folder of frames or a dataset sequence, :func:`odometry`:

1. brings every frame to the model's cylinder at the network's size (equirectangular or other cameras are
   resampled as for ``cylsfm predict``), predicts its depth, and runs the pose network over every window
   of ``seq_length`` frames; each consecutive step ``T_{j->j+1}`` comes from the window centred on ``j``;
2. with ``refine``, refines each step by direct photometric alignment of frame ``j+1`` against frame ``j``
   with frame ``j``'s depth (:mod:`~cylsfm.geometry.align`: wrap-aware, coarse to fine, robust,
   Levenberg-Marquardt), starting from the network's step, or from the visual compass's yaw with the
   network's translation where that aligns better;
3. on rides that come back (``loops``), finds the places seen again and closes the loops with a pose
   graph (:mod:`~cylsfm.odometry.loops`);
4. chains the steps into camera-to-world poses, scales them and writes them.

The run is resolved once (:mod:`~cylsfm.odometry.job`) and goes through named stages, one module each:
:mod:`~cylsfm.odometry.track`, :mod:`~cylsfm.odometry.loops`, :mod:`~cylsfm.odometry.scale`,
:mod:`~cylsfm.odometry.write` (the order: :mod:`~cylsfm.odometry.run`).

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
    odometry.json            frames, unit, scale, seconds and where they went, the loops, the run's
                             settings and their fingerprint (what exports check a given run against)
    depth/FRAME.npy          with depth maps asked for: each frame's depth (the view the network sees)
    points.ply               bundle-adjusted: the triangulated points, coloured (the trajectory's world, unit)
    points.npz               bundle-adjusted: those points with their tracks (the keypoints that saw them)
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
from .job import Job, resolve_job
from .loops import LoopSettings
from .run import OdometryResult, odometry, run_job
from .settings import OdometrySettings

__all__ = [
    "AlignConfig",
    "AlignResult",
    "Job",
    "LoopSettings",
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
    "resolve_job",
    "run_job",
]


class _CallableModule(types.ModuleType):
    """This package, callable as :func:`odometry`."""

    def __call__(self, *args, **kwargs) -> OdometryResult:
        return odometry(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
