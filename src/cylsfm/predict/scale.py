"""One depth scale for every frame of an input (a video, a folder: a ride).

A network's depth is in its own unknown unit, the same for every frame (never normalised frame by frame;
its spread over a ride is what ``cylsfm evaluate depth`` reports as scale consistency). With the camera's
height above a level ground, one factor for the whole input turns it into metres: the camera height over
the median of the ground heights fitted in up to :data:`SAMPLES` frames spread evenly over the input
(:func:`~cylsfm.geometry.ground.ground_height`, :func:`~cylsfm.geometry.ground.metric_scale`). The same
sample gives the pictures' and the preview's one colour range.

The network's scale still wanders from frame to frame by several percent. Given the input's
``cylsfm odometry --refine --depth`` output (with the bundle adjustment), every frame instead takes its
factor to the adjusted points it sees, recorded there (:func:`odometry_factors`): the depth then shares the
trajectory's one scale and unit by construction.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.inputs import InputSource, expected_frames, read_frames
from ..errors import InputError
from ..export.colorize import depth_limits
from ..geometry import Camera, CylindricalCamera
from ..geometry.ground import ground_height, metric_scale
from ..model import Predictor
from ..model.plan import Plan, network_images
from ..runtime import file_id

__all__ = ["SAMPLES", "OdometryFactors", "RideScale", "network_depth", "odometry_factors", "ride_scale"]

#: Frames of an input sampled for its scale and colour range.
SAMPLES = 32


@dataclass(frozen=True)
class RideScale:
    """The scale of every frame of one input.

    Attributes:
        factor: what the network's depth is multiplied by (1 for network units).
        unit: ``"metres"`` or ``"network units"``.
        note: one line saying which scale and how it was found.
        limits: the depths ``(vmin, vmax)`` of the brightest and darkest colours of every picture (in
            ``unit``), ``None`` when the sample has no valid depth.
        sampled: frames sampled; ``ground_fits``: of them, frames with a fitted ground.
        factors: each frame's own factor, in the input's order, instead of ``factor`` (``None``: one for all).
    """

    factor: float
    unit: str
    note: str
    limits: tuple[float, float] | None
    sampled: int
    ground_fits: int | None = None
    factors: tuple[float, ...] | None = None

    def factor_of(self, index: int) -> float:
        """Frame ``index``'s factor (its own, or the input's one).

        Raises:
            InputError: an input of more frames than its own factors.
        """
        if self.factors is None:
            return self.factor
        if index >= len(self.factors):
            raise InputError(
                f"frame {index + 1}: beyond the {len(self.factors)} frames of the odometry given"
            )
        return self.factors[index]

    def to_dict(self) -> dict[str, Any]:
        return {
            "unit": self.unit,
            "factor": self.factor,
            "note": self.note,
            "colour_range": list(self.limits) if self.limits else None,
            "frames_sampled": self.sampled,
            "ground_fits": self.ground_fits,
            "factors": list(self.factors) if self.factors is not None else None,
        }


def network_depth(
    images: torch.Tensor, plan: Plan, seen: torch.Tensor | None, predictor: Predictor
) -> tuple[np.ndarray, Camera]:
    """The network's depth ``float32 [B,h,w]`` of ``images`` ``[B,3,H,W]`` (0 under the mask ``seen``) and
    the camera it is in (the centred crop a model trained on crops sees)."""
    cam = plan.network_input
    win = predictor.window(cam)
    depth = predictor.depth(images, cam, **({"mask": seen} if seen is not None else {}))[:, 0]
    if seen is not None:  # the occluder's depth: unknown
        depth = depth * (seen if win is None else seen[..., win[0] : win[1]])[:, 0].to(depth.device)
    net = cam if predictor.fov >= 360 else cam.crop(predictor.fov)  # type: ignore[attr-defined]
    assert isinstance(net, CylindricalCamera)
    return depth.float().cpu().numpy(), net


def ride_scale(
    source: InputSource,
    plans: Any,
    predictor: Predictor,
    fps: float | None,
    camera_height: float | None,
) -> RideScale:
    """The scale of ``source``'s frames (see the module docstring); ``plans(source, size) -> Plan`` and
    ``plans.mask(source, size)`` give each frame size's plan and mask.

    Raises:
        InputError: ``camera_height`` given but no sampled frame shows a level ground.
    """
    total = expected_frames([source], fps)
    every = max(1, math.ceil(total / SAMPLES)) if total else 10
    depths, heights = [], []
    with torch.inference_mode():
        for i, (_, rgb) in enumerate(read_frames(source, fps)):
            if i % every or len(depths) >= SAMPLES:
                continue
            size = (rgb.shape[1], rgb.shape[0])
            plan = plans(source, size)
            images = network_images([rgb], plan, predictor.device)
            depth, cam = network_depth(images, plan, plans.mask(source, size), predictor)
            depths.append(depth[0])
            heights.append(float(ground_height(torch.from_numpy(depth)[:, None], cam)[0]))
    if camera_height is None:
        limits = depth_limits(np.concatenate([d.ravel() for d in depths])) if depths else None
        note = "network units: one unknown scale, the network's, for every frame (not normalised per frame)"
        return RideScale(1.0, "network units", note, limits, len(depths))
    factor, fits = metric_scale(np.asarray(heights), camera_height)
    limits = depth_limits(np.concatenate([d.ravel() * factor for d in depths]))
    note = (
        f"metres: one factor for every frame, {factor:.4g} m per network unit (the camera {camera_height:g} m "
        f"above the ground fitted in {fits} of {len(depths)} frames sampled, median)"
    )
    return RideScale(factor, "metres", note, limits, len(depths), fits)


@dataclass(frozen=True)
class OdometryFactors:
    """Every frame's factor to the adjusted points, from an output of ``cylsfm odometry`` (``path``: its
    ``odometry.json``), in the trajectory's ``unit``; ``spread``: the factors' coefficient of variation."""

    path: Path
    unit: str
    factors: tuple[float, ...]
    spread: float

    @property
    def id(self) -> str:
        """The file and its content's digest (what a continued run's outputs were made with)."""
        return file_id(self.path)

    def scale(self, scale: RideScale) -> RideScale:
        """``scale`` (the input's sample, for its colour range) with these factors, frame by frame."""
        median = float(np.median(self.factors))
        limits = None if scale.limits is None else (scale.limits[0] * median, scale.limits[1] * median)
        note = (
            f"{self.unit}: the trajectory's one scale, each frame brought to the adjusted points of "
            f"{self.path.parent} (factors median {median:.4g}, spread {self.spread:.1%})"
        )
        return replace(scale, factor=median, unit=self.unit, note=note, limits=limits, factors=self.factors)


def odometry_factors(
    folder: Path, source: InputSource, checkpoint: str, fps: float | None
) -> OdometryFactors:
    """The per-frame depth factors of the input's odometry output ``folder`` (``odometry.json``: made with
    ``--refine --depth`` and the bundle adjustment, for this input, ``checkpoint`` (its identity) and
    ``fps``, every frame).

    Raises:
        InputError: no such output, or one made without the adjustment's depth factors, for another
            input, checkpoint or frame rate, or for another number of frames (naming the file).
    """
    path = Path(folder) / "odometry.json"
    try:
        summary = json.loads(path.read_text())
        settings, depth = summary["settings"], summary["depth_scale"]
        unit = str(summary["unit"])
        factors = tuple(float(f) for f in depth["factors"]) if depth else ()
        spread = float(depth["factor_cv"]) if depth else 0.0
    except FileNotFoundError:
        raise InputError(f"{path}: not found; give the input's output of cylsfm odometry") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: not a summary of cylsfm odometry ({exc})") from None
    if not depth:
        raise InputError(
            f"{path}: has no per-frame depth scale; make it with cylsfm odometry --refine --depth "
            "(the bundle adjustment brings each frame's depth to its points)"
        )
    given = Path(str(settings.get("input"))).resolve()
    if given not in (source.path.resolve(), source.path.resolve().parent):  # a dataset ride: its images/
        raise InputError(f"{path}: made for {settings.get('input')}, not for {source.path}")
    if settings.get("checkpoint") != checkpoint:
        raise InputError(f"{path}: made with another checkpoint ({settings.get('checkpoint')})")
    if settings.get("fps") != fps or settings.get("stride", 1) != 1:
        raise InputError(
            f"{path}: made from other frames (fps {settings.get('fps')}, stride {settings.get('stride')}); "
            f"give the same --fps ({fps}) and every frame"
        )
    total = expected_frames([source], fps)
    if total is not None and total != len(factors):
        raise InputError(f"{path}: {len(factors)} frames, but {source.path} gives {total}")
    if not all(math.isfinite(f) and f > 0 for f in factors):
        raise InputError(f"{path}: depth factors that are not positive numbers")
    return OdometryFactors(path, unit, factors, spread)
