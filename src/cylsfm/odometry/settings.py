"""The settings of :func:`cylsfm.odometry`: one typed object, checked where it is made."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

from ..errors import InputError
from ..geometry import Camera
from ..geometry.align import AlignConfig
from .bundle.stage import RideBundleSettings
from .loops.settings import LoopSettings

__all__ = ["LOOP_MIN_FRAMES", "OdometrySettings"]

#: ``loops="auto"`` looks for loops in rides of at least this many frames.
LOOP_MIN_FRAMES = 200


@dataclass(frozen=True)
class OdometrySettings:
    """How :func:`cylsfm.odometry` reads a ride and what it computes (the defaults of ``cylsfm odometry``).

    Attributes:
        camera: the frames' camera (``camera.json`` or a camera); ``None``: the sequence's own, or full
            cylindrical panoramas of the model's aspect ratio.
        refine: refine every step by direct photometric alignment.
        depth_from: a dataset whose ground-truth depth the refinement uses instead of the network's
            (needs ``refine``).
        camera_height: the camera's height above the ground in metres: scale the result to metres.
        steady_height: the camera stays at one height above the ground (on a vehicle, a helmet on level
            ground): each step's length is brought to one unit by the ground height fitted in its two
            frames (:func:`~cylsfm.geometry.ground.steady_height_steps`), before the loops are closed.
        save_depth_maps: write each frame's depth to ``OUT/depth/FRAME.npy``.
        fps: take about this many frames a second from a video (``None``: every frame); use the rate the
            model was trained at (``cylsfm prepare --fps``), or its steps are of another length.
        stride: every n-th frame.
        keyframe_every: with ``refine``, align each frame to a keyframe, a new one every this many frames
            (1: each frame to the one before); the error then adds up once per keyframe.
        mount_yaw: the azimuth in degrees of the direction of travel in the panorama (0: straight ahead,
            90: to the right, a camera mounted turned left), or ``"auto"``: found from the first frames.
        batch_size: windows and pairs per call.
        device: ``auto``, ``cpu``, ``cuda``, ``cuda:N``.
        amp: the networks in bf16 where it is native (:class:`~cylsfm.model.Predictor`); ``False``:
            fp32 (not with a ready predictor).
        align: the refinement's settings.
        progress: show a progress bar.
        pose_iterations: :class:`~cylsfm.model.Predictor`'s further pose passes (``None``: the model's
            default; not with a ready predictor).
        mask: an image of the frames' pixels that see the scene (white) and of an occluder fixed to the
            camera, a helmet or a mount (black), in the frames' own geometry; the compass, the refinement
            and the search for the direction of travel leave the occluder out. ``None``: a dataset
            sequence's own ``mask.png`` when it has one; ``False``: every pixel.
        loops: close loops (:mod:`~cylsfm.odometry.loops`): ``True``,
            ``False``, or ``"auto"``: when the ride has at least :data:`LOOP_MIN_FRAMES` frames and the
            model reads full panoramas.
        loop: how loops are looked for and accepted.
        bundle: after the loops, adjust the poses together with sparse points triangulated from SIFT
            features matched across frames (:mod:`~cylsfm.odometry.bundle`), seeded and held by the
            odometry: ``True``, ``False``, or ``"auto"``: with ``refine`` (see :attr:`adjusts`).
        bundle_settings: how.

    Raises:
        InputError: for a value out of range or ``depth_from`` without ``refine``.
    """

    camera: str | os.PathLike[str] | Camera | None = None
    refine: bool = False
    depth_from: str | os.PathLike[str] | None = None
    camera_height: float | None = None
    steady_height: bool = False
    save_depth_maps: bool = False
    fps: float | None = None
    stride: int = 1
    keyframe_every: int = 1
    mount_yaw: float | str = "auto"
    batch_size: int = 8
    device: str = "auto"
    amp: bool = True
    align: AlignConfig = field(default_factory=AlignConfig)
    progress: bool = True
    pose_iterations: int | None = None
    mask: str | os.PathLike[str] | bool | None = None
    loops: bool | str = "auto"
    loop: LoopSettings = field(default_factory=LoopSettings)
    bundle: bool | str = "auto"
    bundle_settings: RideBundleSettings = field(default_factory=RideBundleSettings)

    def __post_init__(self) -> None:
        if self.keyframe_every < 1:
            raise InputError(f"keyframe_every must be at least 1, got {self.keyframe_every}")
        mount = self.mount_yaw
        if not (mount == "auto" or (isinstance(mount, int | float) and math.isfinite(mount))):
            raise InputError(f"mount_yaw must be 'auto' or an azimuth in degrees, got {mount!r}")
        if self.batch_size < 1:
            raise InputError(f"batch_size must be at least 1, got {self.batch_size}")
        height = self.camera_height
        if height is not None and not (math.isfinite(height) and height > 0):
            raise InputError(f"camera_height must be a positive number of metres, got {height}")
        if self.mask is True:
            raise InputError("mask: give the mask image's path, None (a sequence's own) or False (none)")
        if not (self.loops in (True, False) or self.loops == "auto"):
            raise InputError(f"loops must be True, False or 'auto', got {self.loops!r}")
        if not (self.bundle in (True, False) or self.bundle == "auto"):
            raise InputError(f"bundle must be True, False or 'auto', got {self.bundle!r}")
        if self.depth_from is not None and not self.refine:
            raise InputError("depth_from gives the refinement its depth: it needs refine=True (--refine)")

    @property
    def adjusts(self) -> bool:
        """Whether the bundle adjustment runs: asked for, or ``"auto"`` with ``refine``."""
        return bool(self.refine) if self.bundle == "auto" else bool(self.bundle)

    @property
    def find_mount(self) -> bool:
        """Whether the direction of travel is to be found (not given)."""
        return self.mount_yaw == "auto"
