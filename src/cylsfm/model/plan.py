"""Which inputs a model can take, and how they reach it: the model's cylinder and each input's plan.

The networks expect the panoramas they were trained on: full 360-degree cylindrical panoramas whose rows
span ``h`` in ``[-vfov_h, vfov_h]`` (``Predictor.vfov_h``, :func:`model_vfov_h`) with the training aspect ratio; for a model
trained on centred crops (``data.fov < 360``), the network sees only the crop of them.

* Without a camera, an input must have that aspect ratio (width/height within :data:`ASPECT_TOLERANCE`);
  it is taken as ``CylindricalCamera.full(w, h, vfov_h)``. A 2:1 input is taken as an equirectangular
  360-degree panorama (the usual output of 360 cameras) unless the model's own aspect is 2:1; the plan's
  ``note`` says so.
* A full cylindrical panorama of the training vertical field of view is used as it is.
* Any other camera (an equirectangular 360-degree image, a cylinder of another vertical field of view, a
  partial panorama, a pinhole photograph) is resampled (:func:`cylsfm.data.convert.to_cylinder`) into the
  model's cylinder (:func:`model_camera`) at the network's input size, when it covers at least
  :data:`MIN_COVERAGE` of the pixels the network sees. A full 360-degree source always does. A pinhole
  view never covers half of a full panorama: a model trained on full panoramas would see mostly blank
  panorama, which it has never seen, so it refuses pinhole input; a model trained on a crop takes a
  pinhole view (or a partial panorama) that covers the crop.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..data.convert import to_cylinder
from ..data.io import load_mask
from ..errors import CylsfmError
from ..geometry import Camera, CylindricalCamera, EquirectangularCamera, PinholeCamera
from .build import DEFAULT_VFOV_H, LoadedModels, training_vfov_h
from .config import TrainConfig
from .predictor import Predictor

__all__ = [
    "ASPECT_TOLERANCE",
    "DEFAULT_VFOV_H",
    "MIN_COVERAGE",
    "Plan",
    "coverage",
    "model_camera",
    "model_vfov_h",
    "network_images",
    "network_mask",
    "plan_input",
]

#: Relative tolerance on the aspect ratio (and vertical field of view) matching the model's.
ASPECT_TOLERANCE = 0.02
#: Smallest fraction of the network's view that a converted input must cover (the rest would be blank).
MIN_COVERAGE = 0.9


def model_vfov_h(model: Predictor | LoadedModels | TrainConfig) -> float:
    """The vertical extent ``vfov_h`` (rows span ``h`` in ``[-vfov_h, vfov_h]``) the model was trained on.

    ``model_vfov_h(predictor)`` is ``predictor.vfov_h``: the run metadata of its checkpoint
    (:func:`~cylsfm.model.build.training_vfov_h`). Given a configuration alone (the earlier call form,
    ``model_vfov_h(predictor.config)``), which records no measurement, only the fallbacks of checkpoints
    without one: the training dataset's ``camera.json`` when ``config.data.root`` is still there, otherwise
    :data:`DEFAULT_VFOV_H`.
    """
    if isinstance(model, Predictor | LoadedModels):
        return model.vfov_h
    return training_vfov_h({}, model)


def model_camera(predictor: Predictor, vfov_h: float | None = None) -> CylindricalCamera:
    """The full 360-degree cylinder the model expects, at the network's input size.

    ``CylindricalCamera.full(W, H, vfov_h)`` with ``(W, H)`` the network's input size (for a model trained
    on ``fov``-degree crops, ``W`` is the full turn around them: ``config.data.width`` is the panorama's
    width, the crop comes after it). ``vfov_h`` defaults to the model's own, ``predictor.vfov_h``.
    """
    if vfov_h is None:
        vfov_h = predictor.vfov_h
    return CylindricalCamera.full(predictor.size[0], predictor.size[1], vfov_h)


def _aspect_ok(a: float, b: float) -> bool:
    return abs(a / b - 1.0) <= ASPECT_TOLERANCE


def coverage(camera: Camera, target: CylindricalCamera, window: tuple[int, int] | None) -> float:
    """Fraction (0..1) of the pixels of ``target`` in columns ``window`` (all: ``None``) that ``camera``
    sees, as :func:`~cylsfm.data.convert.to_cylinder` samples them (one ray a pixel)."""
    ones = torch.ones(1, 1, camera.height, camera.width)
    _, mask = to_cylinder(ones, camera, target, supersample=1, return_mask=True)
    if window is not None:
        mask = mask[..., window[0] : window[1]]
    return float(mask.float().mean())


@dataclass(frozen=True)
class Plan:
    """How frames of one size reach the network: their camera, and the cylinder they are converted to."""

    camera: Camera
    convert_to: CylindricalCamera | None = None
    note: str | None = None  # how the camera was chosen, when the user did not say

    @property
    def network_input(self) -> Camera:
        """The camera of the frames given to the :class:`~cylsfm.model.Predictor`."""
        return self.convert_to if self.convert_to is not None else self.camera


def _checked_coverage(cam: Camera, target: CylindricalCamera, predictor: Predictor, camera_path: str) -> None:
    covered = coverage(cam, target, predictor.window(target))
    if covered >= MIN_COVERAGE:
        return
    view = "full 360-degree panoramas" if predictor.fov >= 360 else f"{predictor.fov:g}-degree crops"
    elevation = math.degrees(math.atan(target.height / (2.0 * float(target.fy))))
    raise CylsfmError(
        f"{camera_path}: this {cam.model} camera covers {covered:.0%} of the view of the model, which was "
        f"trained on {view} of cylindrical panoramas (elevation within +-{elevation:.0f} degrees); "
        f"at least {MIN_COVERAGE:.0%} is needed, the rest would be blank. Give it 360-degree footage "
        f"(equirectangular or cylindrical), or use a model trained on a crop the camera covers "
        f"(cylsfm train --fov DEG)"
    )


def plan_input(
    path: object,
    size: tuple[int, int],
    predictor: Predictor,
    vfov_h: float,
    camera: Camera | None,
    camera_path: str | None,
) -> Plan:
    """The :class:`Plan` of frames of ``size`` ``(W, H)`` from input ``path``, seen by ``camera``.

    Raises:
        CylsfmError: the frames do not suit the model (see the module docstring); the message names the
            input or the camera file.
    """
    w, h = size
    target = model_camera(predictor, vfov_h)
    want = target.width / target.height
    if camera is None:
        if _aspect_ok(w / h, 2.0) and not _aspect_ok(want, 2.0):  # unambiguous: the whole sphere
            note = f"{w}x{h} frames taken as equirectangular 360-degree panoramas (--camera says otherwise)"
            return Plan(EquirectangularCamera.full(w, h), convert_to=target, note=note)
        if not _aspect_ok(w / h, want):
            raise CylsfmError(
                f"{path}: frames are {w}x{h} (aspect {w / h:.3f}) but the model takes full 360-degree "
                f"cylindrical panoramas of aspect {want:.3f} (width/height, e.g. {target.width}x{target.height}); "
                f"for other footage pass --camera camera.json describing it (cylindrical, equirectangular, or "
                f"pinhole for a model trained on crops; see 'cylsfm camera')"
            )
        return Plan(CylindricalCamera.full(w, h, vfov_h))
    cam = camera
    if cam.size != (w, h):
        if not _aspect_ok((w / h), cam.width / cam.height):
            raise CylsfmError(
                f"{path}: frames are {w}x{h} but {camera_path} describes {cam.width}x{cam.height} images"
            )
        cam = cam.resized(w, h)
    if not isinstance(cam, CylindricalCamera | EquirectangularCamera | PinholeCamera):
        raise CylsfmError(f"{camera_path}: unsupported camera model {cam.model!r}")
    if isinstance(cam, CylindricalCamera) and cam.wraps:
        cam_vfov = cam.height / (2.0 * float(cam.fy))
        centred = abs(float(cam.cy) - (cam.height - 1) / 2) <= 0.01 * cam.height
        if centred and _aspect_ok(cam_vfov, vfov_h):
            return Plan(cam)
    if not cam.wraps:
        _checked_coverage(cam, target, predictor, str(camera_path))
    return Plan(cam, convert_to=target)


def network_images(batch: Sequence[np.ndarray], plan: Plan, device: torch.device) -> torch.Tensor:
    """``uint8 [H,W,3]`` frames -> ``[B,3,H',W']`` in [0, 1] on ``device``, in ``plan.network_input``.

    Frames go to the device as ``uint8`` (4x less to copy) and are converted one at a time, so that large
    360-degree frames never sit on the device as a whole batch.
    """
    frames = []
    for rgb in batch:
        x = torch.from_numpy(np.require(rgb, np.uint8, ["C", "W"])).to(device).permute(2, 0, 1)[None].float()
        x = x / 255
        if plan.convert_to is not None:
            x = to_cylinder(x, plan.camera, plan.convert_to).clamp(0, 1)
        frames.append(x)
    return torch.cat(frames)


def network_mask(path: Any, frames: tuple[int, int], plan: Plan, size: tuple[int, int]) -> torch.Tensor:
    """A mask image of the input's frames -> ``float [1,1,h,w]`` in ``{0, 1}`` at the network's ``size``
    ``(w, h)``: 1 where the scene is seen (white in the file) over at least 99% of a pixel's area, 0 on an
    occluder fixed to the camera (black) and where a converted input has no pixels.

    Args:
        path: the mask file, in the frames' own geometry (``frames``: their size ``(W, H)``); any size of
            the same aspect ratio.
        plan: how the frames reach the network (:func:`plan_input`).

    Raises:
        CylsfmError: naming the file: unreadable, or not of the frames' aspect ratio.
    """
    from PIL import Image

    w, h = frames
    try:
        with Image.open(path) as im:
            mw, mh = im.size
    except Exception:
        load_mask(path)  # raises the project's error naming the file
        raise
    if not _aspect_ok(mw / mh, w / h):
        raise CylsfmError(
            f"{path}: the mask is {mw}x{mh} but the frames are {w}x{h}: a mask must cover the frames as they "
            "are (same aspect ratio; white where the scene is seen, black on the mount or helmet)"
        )
    x = torch.from_numpy(load_mask(path, (w, h)))[None, None]
    if plan.convert_to is not None:
        x, has = to_cylinder(x, plan.camera, plan.convert_to, return_mask=True)
        x = x * has.to(x.dtype)
    if (x.shape[-1], x.shape[-2]) != tuple(size):
        x = torch.nn.functional.interpolate(x, size=(size[1], size[0]), mode="area")
    return (x > 0.99).float()
