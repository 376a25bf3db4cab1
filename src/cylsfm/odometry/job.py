"""One run of :func:`cylsfm.odometry` resolved once: the ride, the settings, the networks, how the frames
reach them, the mask, the depth source and the fingerprints of what decides the result. Every stage of
the pipeline (:mod:`cylsfm.odometry.run`) reads the :class:`Job`; nothing is opened or loaded twice."""

from __future__ import annotations

import hashlib
import logging
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .._version import __version__
from ..errors import CylsfmError, InputError
from ..geometry import Camera, load_camera
from ..model import Predictor
from ..model.checkpoint import checkpoint_id
from ..model.plan import Plan, network_images, network_mask, plan_input
from ..runtime import fingerprint
from .depth import DepthSource
from .frames import Ride, depth_files, open_ride
from .settings import LOOP_MIN_FRAMES, OdometrySettings

__all__ = ["Job", "network_size", "resolve_job", "ride_mask", "ride_plan"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Job:
    """Everything a run's stages read, resolved once by :func:`resolve_job`.

    Attributes:
        ride: the input.
        settings: what the user asked for.
        predictor: the networks (loaded once).
        plan: how the ride's frames reach the networks.
        camera: the camera of the network-size frames (``predictor.size``) given to the tracker.
        view: the camera of what the networks see of them (all of a full panorama).
        mask_file: the mask image in use (``None``: every pixel).
        mask: ``[1,1,H,W]`` at the network's size, 1 where the scene is seen (``None``: every pixel).
        depth: each frame's depth (the network's, or ground truth).
        mount_yaw: the direction of travel given (radians); ``None``: found from the frames, or none.
        find_mount: whether the direction of travel is to be found.
        places: whether every frame's place descriptor is kept (loop closure: full panoramas only).
        out: the output directory.
        identity: what decides the trajectory (input, checkpoint, camera and every option that changes
            it), recorded in ``odometry.json``; its :attr:`fingerprint` tells whether an output is this
            run's.
        state_key: the fingerprint of what decides the saved progress (a state with another is not
            continued).
    """

    ride: Ride
    settings: OdometrySettings
    predictor: Predictor
    plan: Plan
    camera: Camera
    view: Camera
    mask_file: Path | None
    mask: Tensor | None
    depth: DepthSource
    mount_yaw: float | None
    find_mount: bool
    places: bool
    out: Path
    identity: dict[str, Any]
    state_key: str

    @property
    def fingerprint(self) -> str:
        """The fingerprint of :attr:`identity`."""
        return fingerprint(self.identity)

    def images(self, frames: list[np.ndarray]) -> Tensor:
        """``uint8 [H,W,3]`` frames -> network-size images ``[B,3,H',W']`` in [0, 1] on the networks'
        device."""
        return network_size(network_images(frames, self.plan, self.predictor.device), self.predictor.size)

    def view_of(self, images: Tensor) -> Tensor:
        """Network-size images ``[...,H,W]`` -> the part the networks see (all of a full panorama)."""
        win = self.predictor.window(self.camera)
        return images if win is None else images[..., win[0] : win[1]]

    @property
    def view_mask(self) -> Tensor | None:
        """The mask ``[1,1,h,w]`` of what the networks see (``None``: none)."""
        return None if self.mask is None else self.view_of(self.mask)

    def loops_wanted(self, frames: int) -> bool:
        """Whether a ride of ``frames`` frames closes its loops (``loops="auto"``: long rides)."""
        loops = self.settings.loops
        return self.places and (loops is True or frames >= LOOP_MIN_FRAMES)


def resolve_job(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str] | Predictor,
    out: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
) -> Job:
    """Open the ride, load the networks (``checkpoint`` itself when it is a ready predictor), plan how the
    frames reach them, read the mask and the depth source, and fingerprint the run.

    Raises:
        CylsfmError: an input, camera, mask, checkpoint or dataset problem, naming the file.
        InputError: options that do not suit the model (a direction of travel for a model of crops,
            loops for a model that does not read full panoramas).
    """
    opt = settings or OdometrySettings()
    ride = open_ride(input, opt.fps, opt.stride)
    predictor = (
        checkpoint
        if isinstance(checkpoint, Predictor)
        else Predictor.from_checkpoint(checkpoint, opt.device, opt.pose_iterations, opt.amp)
    )
    plan = ride_plan(ride, predictor, opt.camera)
    camera = plan.network_input.resized(*predictor.size)
    view = predictor.network_camera(camera)
    mask_file = ride_mask(ride, opt.mask)
    mask = network_mask(mask_file, ride.size, plan, predictor.size) if mask_file is not None else None
    files = _true_depth_files(opt.depth_from, ride, plan)
    turnable = predictor.fov >= 360 and predictor.wrap
    if opt.mount_yaw != "auto" and opt.mount_yaw and not turnable:
        raise InputError(f"mount_yaw: a {predictor.fov:g}-degree model reads no other direction than its own")
    given = None if opt.find_mount or not turnable else math.radians(float(opt.mount_yaw))
    places = bool(opt.loops) and view.wraps
    if opt.loops is True and not places:
        raise InputError(f"{ride.path}: loops need a model that reads full panoramas (this one reads a crop)")
    identity = _identity(ride, checkpoint, plan, predictor, opt, mask_file)
    return Job(
        ride=ride,
        settings=opt,
        predictor=predictor,
        plan=plan,
        camera=camera,
        view=view,
        mask_file=mask_file,
        mask=mask,
        depth=DepthSource(predictor, camera, mask, files),
        mount_yaw=given,
        find_mount=opt.find_mount and turnable,
        places=places,
        out=Path(out),
        identity=identity,
        state_key=fingerprint(_state_identity(identity, opt)),
    )


def ride_plan(ride: Ride, predictor: Predictor, camera: Any) -> Plan:
    """How the ride's frames reach the network (its camera: the one given, or a dataset sequence's own);
    a note on how the camera was chosen, when the user did not say, goes to the log."""
    cam = load_camera(camera) if isinstance(camera, str | os.PathLike) else camera
    cam_name = (
        str(camera) if isinstance(camera, str | os.PathLike) else ("the given camera" if camera else None)
    )
    if cam is None and ride.camera is not None:
        cam, cam_name = ride.camera, str(ride.path / "camera.json")
    plan = plan_input(ride.path, ride.size, predictor, predictor.vfov_h, cam, cam_name)
    if plan.note:
        log.info("%s: %s", ride.path, plan.note)
    return plan


def ride_mask(ride: Ride, mask: Any) -> Path | None:
    """The mask image to use: the one given, else a dataset sequence's own (``False``: none)."""
    if mask is False:
        return None
    if mask is not None:
        return Path(mask)
    return ride.sequence.mask if ride.sequence is not None else None


def _identity(
    ride: Ride,
    checkpoint: Any,
    plan: Plan,
    predictor: Predictor,
    opt: OdometrySettings,
    mask_file: Path | None,
) -> dict[str, Any]:
    """What decides the trajectory: a run with the same identity writes the same trajectory."""
    return {
        "input": str(Path(ride.path).resolve()),
        "checkpoint": _checkpoint_id(checkpoint),
        "camera": plan.network_input.to_dict(),
        "depth_from": str(Path(opt.depth_from).resolve()) if opt.depth_from is not None else None,
        "refine": opt.refine,
        "fps": opt.fps,
        "stride": opt.stride,
        "keyframe_every": opt.keyframe_every,
        "mount_yaw": opt.mount_yaw,
        "pose_iterations": predictor.pose_iterations,
        "networks": str(predictor.dtype or torch.float32),  # bf16 where native (amp), else fp32
        "mask": _file_id(mask_file),
        "align": asdict(opt.align),
        "camera_height": opt.camera_height,
        "steady_height": opt.steady_height,
        "loops": opt.loops,
        "loop": asdict(opt.loop),
        "bundle": asdict(opt.bundle_settings) if opt.adjusts else False,
        "version": __version__,
    }


def _state_identity(identity: dict[str, Any], opt: OdometrySettings) -> dict[str, Any]:
    """What decides the saved progress: the tracking's identity (the loops keep their own key in the
    state: other loop settings look again on the same tracking) and which depth files are written (in
    network units, or kept apart until their scale is known, in metres or the adjusted points': so that
    scale counts; scaled by the points, the depth files depend on every stage)."""
    later = ("camera_height", "steady_height", "loop", "bundle")  # stages after the tracking
    if opt.save_depth_maps and opt.adjusts:  # the depth files are scaled by the points: every stage counts
        later = ()
    tracking = {k: v for k, v in identity.items() if k not in later}
    return {
        **tracking,
        "ground_fit": opt.camera_height is not None or opt.steady_height,  # every frame's ground height
        "depth_maps": opt.save_depth_maps,
        "depth_scale": (
            {"camera_height": opt.camera_height, "points": opt.adjusts} if opt.save_depth_maps else None
        ),
    }


def _checkpoint_id(checkpoint: Any) -> str:
    """The checkpoint's identity: a ready predictor's is its file's, when it was loaded from one."""
    if isinstance(checkpoint, Predictor):
        path = checkpoint.models.path
        return checkpoint_id(path) if path.is_file() else f"predictor {id(checkpoint)}"
    return checkpoint_id(checkpoint)


def _file_id(path: Path | None) -> str | None:
    """A file's path and content digest (what a saved state was computed with)."""
    if path is None:
        return None
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    except OSError as exc:
        raise CylsfmError(f"{path}: cannot read the mask ({exc.strerror or exc})") from None
    return f"{path.resolve()} {digest}"


def _true_depth_files(depth_from: Any, ride: Ride, plan: Plan) -> list[Path] | None:
    """The ground-truth depth files of ``depth_from`` for the ride's frames (``None``: not asked for)."""
    if depth_from is None:
        return None
    if plan.convert_to is not None:
        raise CylsfmError(
            f"{ride.path}: ground-truth depth needs frames the model takes as they are (no conversion)"
        )
    return depth_files(depth_from, ride)


def network_size(images: Tensor, size: tuple[int, int]) -> Tensor:
    """``[B,3,H,W]`` -> the network's size ``(W, H)`` by area averaging (as the predictor resizes)."""
    w, h = size
    if images.shape[-2:] == (h, w):
        return images
    return F.interpolate(images, size=(h, w), mode="area")
