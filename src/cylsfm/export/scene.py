"""A panorama and its depth, ready to export: from a trained checkpoint or from a depth file, in relative
or metric scale.

:func:`load_scene` reads a panorama (any image ``cylsfm predict`` takes) and either predicts its depth with
a checkpoint (the panorama as the network sees it: converted to the model's cylinder when it is not one)
or reads a depth file (``.npy``, cylindrical depth in metres as in the dataset format, 0 unknown) of a
cylindrical panorama, at the panorama's size or a smaller one of the same aspect ratio. A scene keeps the
panorama it came from: :meth:`Scene.within` brings it to a chosen number of pixels (a mesh's vertex
budget), with the colours of the original panorama and the depth upsampled guided by them. The scale of a network's depth is unknown: :func:`Scene.to_metres` fixes it from the
camera's height above a level ground (the fit of :func:`~cylsfm.geometry.ground.ground_height`), and
:func:`Scene.normalised` gives one of a chosen median depth (a comfortable stereo for VR when no metres are
known). :attr:`Scene.scale_note` says which, for the outputs' headers.

A mask (white where the scene is seen, black on an occluder fixed to the camera: a helmet, a mount; a
dataset frame's sequence ``mask.png`` by default) keeps the occluder out of the geometry: the network sees
it filled from its surroundings, and its depth is unknown (0), so no mesh vertex and no stereo parallax
comes from it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.io import image_size, load_depth, load_image
from ..errors import CylsfmError, InputError
from ..geometry import Camera, CylindricalCamera, load_camera
from ..geometry.ground import ground_height, metric_scale

__all__ = ["Scene", "SceneFunction", "load_scene", "scene_function"]


@dataclass(frozen=True)
class Scene:
    """A cylindrical panorama with depth.

    Attributes:
        image: ``uint8 [H,W,3]`` colours in ``camera``.
        depth: ``float32 [H,W]`` cylindrical depth in ``camera`` (0: unknown, e.g. the sky of ground truth).
        camera: the panorama's cylindrical camera.
        unit: ``"metres"`` or ``"network units"`` (relative: one unknown scale).
        scale_note: how the scale was found, one line for file headers.
    """

    image: np.ndarray
    depth: np.ndarray
    camera: CylindricalCamera
    unit: str
    scale_note: str
    source: tuple[np.ndarray, Camera] | None = None  # the original frame and its camera, for sharper colour

    @property
    def full_width(self) -> int:
        """The width of the panorama the scene came from (its own colours' resolution)."""
        if self.source is None:
            return self.camera.width
        rgb, src = self.source
        return max(self.camera.width, round(2 * np.pi * float(src.fx))) if src.wraps else rgb.shape[1]

    def colour_at_width(self, width: int) -> tuple[np.ndarray, CylindricalCamera]:
        """The panorama's colours ``uint8 [H',W,3]`` at ``width`` (same field of view) and their camera:
        from the original frame when known (else from ``image``), area-averaged or interpolated
        (:class:`~cylsfm.data.convert.Resampler`)."""
        from ..data.convert import Resampler

        w, h = self.camera.size
        if width < 8:
            raise InputError(f"width must be at least 8, got {width}")
        cam = self.camera.resized(width, max(2, round(width * h / w)))
        assert isinstance(cam, CylindricalCamera)
        if width == w and self.source is None:
            return self.image, cam
        rgb, src = self.source if self.source is not None else (self.image, self.camera)
        return Resampler(src, cam).frames([np.ascontiguousarray(rgb)])[0], cam

    def at_width(self, width: int) -> Scene:
        """The scene resampled to a panorama ``width`` wide (same field of view): colour as
        :meth:`colour_at_width`; depth upsampled guided by those colours
        (:func:`~cylsfm.export.upsample.guided_upsample`: depth edges follow the colour edges), or
        area-averaged where known when made smaller."""
        from ..data.convert import Resampler
        from .upsample import guided_upsample

        if width == self.camera.width:
            return self
        colour, cam = self.colour_at_width(width)
        if width > self.camera.width:
            depth = guided_upsample(self.depth, colour, wrap=self.camera.wraps)
            return replace(self, image=colour, depth=depth, camera=cam)
        known = torch.from_numpy((self.depth > 0).astype(np.float32))[None, None]
        d = torch.from_numpy(np.where(self.depth > 0, self.depth, 0).astype(np.float32))[None, None]
        to = Resampler(self.camera, cam)
        weight = to(known)
        small = torch.where(weight >= 0.5, to(d) / weight.clamp(min=1e-6), torch.zeros(()))
        return replace(self, image=colour, depth=small[0, 0].numpy().astype(np.float32), camera=cam)

    def within(self, vertices: int) -> Scene:
        """The scene at the largest width whose pixels number at most ``vertices`` (at most the original
        panorama's width, at least the depth's when that fits): a mesh density chosen by a budget, not by
        the network's size."""
        if vertices < 64:
            raise InputError(f"the vertex budget must be at least 64, got {vertices}")
        w, h = self.camera.size
        width = min(int(np.sqrt(vertices * w / h)), self.full_width)
        while width > 8 and width * max(2, round(width * h / w)) > vertices:
            width -= 1
        return self.at_width(max(8, width))

    @property
    def metric(self) -> bool:
        return self.unit == "metres"

    def scaled(self, factor: float, unit: str, note: str) -> Scene:
        return replace(self, depth=(self.depth * factor).astype(np.float32), unit=unit, scale_note=note)

    def to_metres(self, camera_height: float) -> Scene:
        """The depth rescaled so that the fitted ground lies ``camera_height`` metres below the camera.

        Raises:
            InputError: no level ground below the horizon.
        """
        h = ground_height(torch.from_numpy(self.depth)[None, None], self.camera).numpy()
        factor, _ = metric_scale(h, camera_height)
        note = (
            f"metres: the ground fitted {h[0]:.4g} {self.unit} below the camera, set to {camera_height:g} m"
        )
        return self.scaled(factor, "metres", note)

    def normalised(self, median: float) -> Scene:
        """The depth rescaled to a median of ``median`` over the known pixels (unit kept as relative)."""
        known = self.depth[self.depth > 0]
        if not len(known):
            raise InputError("the depth map has no known pixel")
        factor = median / float(np.median(known))
        return self.scaled(factor, self.unit, f"{self.scale_note}; rescaled to a median depth of {median:g}")


def _full_cylinder(width: int, height: int, camera: Camera | None, where: str) -> CylindricalCamera:
    if camera is None:
        return CylindricalCamera.full(width, height)
    if not isinstance(camera, CylindricalCamera) or not camera.wraps:
        raise CylsfmError(f"{where}: exporting needs a full 360-degree cylindrical panorama's camera")
    return camera if camera.size == (width, height) else camera.resized(width, height)  # type: ignore[return-value]


def _dataset_camera(pano: Path) -> Camera | None:
    """The ``camera.json`` of the dataset sequence a frame ``SEQ/images/X.png`` belongs to, if any."""
    path = pano.parent.parent / "camera.json"
    return load_camera(path) if pano.parent.name == "images" and path.is_file() else None


def _dataset_mask(pano: Path) -> Path | None:
    """The ``mask.png`` of the dataset sequence a frame ``SEQ/images/X.png`` belongs to, if any."""
    path = pano.parent.parent / "mask.png"
    return path if pano.parent.name == "images" and path.is_file() else None


def load_scene(
    pano: str | os.PathLike[str],
    depth: str | os.PathLike[str] | None = None,
    checkpoint: str | os.PathLike[str] | None = None,
    camera: str | os.PathLike[str] | None = None,
    device: str = "auto",
    mask: str | os.PathLike[str] | bool | None = None,
    amp: bool = True,
) -> Scene:
    """The panorama ``pano`` with its depth from ``depth`` (a ``.npy`` file) or ``checkpoint``.

    ``camera``: the panorama's camera.json (default: a dataset frame's sequence camera, else a full
    cylinder of +-45 degrees for a depth file, or as ``cylsfm predict`` decides for a checkpoint).
    ``mask``: an image of the panorama's aspect ratio, black on an occluder fixed to the camera, whose
    depth is then unknown (``None``: a dataset frame's sequence ``mask.png`` when there is one; ``False``:
    none). ``amp``: the network in bf16 where it is native (:class:`~cylsfm.model.Predictor`).

    Raises:
        CylsfmError: naming the file: neither or both of ``depth`` and ``checkpoint``, an unreadable or
            mismatched depth file, a camera that does not suit.
    """
    pano = Path(pano)
    if (depth is None) == (checkpoint is None):
        raise InputError("give the depth either from a checkpoint or from a depth file, not both or neither")
    cam = load_camera(camera) if camera is not None else _dataset_camera(pano)
    mask_file = _dataset_mask(pano) if mask is None else (None if mask is False else Path(mask))  # type: ignore[arg-type]
    if checkpoint is not None:
        chosen = camera if camera is not None else cam
        return scene_function(pano, checkpoint, chosen, device, mask_file, amp)(load_image(pano))
    w, h = image_size(pano)
    cyl = _full_cylinder(w, h, cam, str(camera or pano))
    d = load_depth(Path(depth))  # type: ignore[arg-type]
    dh, dw = d.shape
    if (dw, dh) != (w, h) and (dw > w or abs(dw / dh - w / h) > 0.02 * (w / h)):
        raise CylsfmError(
            f"{depth}: the depth is {dw}x{dh}, the panorama {w}x{h}: neither the same size nor a smaller one "
            "of the same aspect ratio"
        )
    if mask_file is not None:
        d = np.where(_mask_at(mask_file, (dw, dh)) > 0, d, np.float32(0)).astype(np.float32)
    rgb = load_image(pano)
    if (dw, dh) == (w, h):
        return Scene(rgb, d, cyl, "metres", "metres (the depth file's)")
    coarse = cyl.resized(dw, dh)
    assert isinstance(coarse, CylindricalCamera)
    from ..data.convert import Resampler

    image = Resampler(cyl, coarse).frames([rgb])[0]
    return Scene(image, d, coarse, "metres", "metres (the depth file's)", source=(rgb, cyl))


def _mask_at(path: Path, size: tuple[int, int]) -> np.ndarray:
    """The mask file at ``size`` ``(W, H)`` (``float32 [H,W]``, 1: the scene), of the same aspect ratio."""
    from ..data.io import load_mask

    mw, mh = image_size(path)
    w, h = size
    if abs(mw / mh - w / h) > 0.02 * (w / h):
        raise CylsfmError(f"{path}: the mask is {mw}x{mh}, the panorama {w}x{h}: not the same aspect ratio")
    return load_mask(path, size)


def scene_function(
    where: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str],
    camera: str | os.PathLike[str] | Camera | None = None,
    device: str = "auto",
    mask: str | os.PathLike[str] | None = None,
    amp: bool = True,
) -> SceneFunction:
    """A :class:`SceneFunction` predicting frames of input ``where`` (a video's frames) with ``checkpoint``;
    ``camera``: the frames' camera (a camera.json or a camera; ``None``: as ``cylsfm predict`` decides).
    ``mask``: an image of the frames' aspect ratio, black on an occluder fixed to the camera: filled in
    what the network sees, its depth unknown (0). ``amp``: as for :func:`load_scene`."""
    from ..model import Predictor

    predictor = Predictor.from_checkpoint(checkpoint, device, amp=amp)
    if predictor.fov < 360:
        raise CylsfmError(
            f"{checkpoint}: the model sees {predictor.fov:g}-degree crops; exporting needs 360 degrees"
        )
    return SceneFunction(predictor, where, str(checkpoint), camera, mask)


class SceneFunction:
    """Frames ``rgb uint8 [H,W,3]`` of one input -> their :class:`Scene` with the network's depth: one
    frame (``scene_of(rgb)``) or several at one network call (:meth:`many`, a video's frames). The plan (the
    camera conversion) is made once per frame size. Made by :func:`scene_function`."""

    def __init__(
        self,
        predictor: Any,
        where: str | os.PathLike[str],
        name: str,
        camera: str | os.PathLike[str] | Camera | None,
        mask: str | os.PathLike[str] | None,
    ) -> None:
        self.predictor, self.where, self.name, self.mask = predictor, where, name, mask
        self.camera = load_camera(camera) if isinstance(camera, str | os.PathLike) else camera
        self.label = str(camera) if isinstance(camera, str | os.PathLike) else str(where)
        self.plans: dict[tuple[int, int], tuple[Any, torch.Tensor | None]] = {}

    def _plan(self, size: tuple[int, int]) -> tuple[Any, torch.Tensor | None]:
        from ..model.plan import network_mask, plan_input

        if size not in self.plans:
            p = self.predictor
            plan = plan_input(self.where, size, p, p.vfov_h, self.camera, self.label)
            seen = None if self.mask is None else network_mask(self.mask, size, plan, plan.network_input.size)
            self.plans[size] = (plan, seen)
        return self.plans[size]

    def __call__(self, rgb: np.ndarray, depth: np.ndarray | None = None) -> Scene:
        """The frame's scene; ``depth``: its depth as this function gave it before (no network then)."""
        return self.many([rgb])[0] if depth is None else self._scenes([rgb], depth[None])[0]

    def many(self, rgbs: list[np.ndarray]) -> list[Scene]:
        """The scenes of frames ``rgbs`` (of one size: in one network call; else one by one)."""
        if len({r.shape for r in rgbs}) > 1:
            return [self(r) for r in rgbs]
        return self._scenes(rgbs, None)

    def _scenes(self, rgbs: list[np.ndarray], depth: np.ndarray | None) -> list[Scene]:
        from ..model.plan import network_images

        plan, seen = self._plan((rgbs[0].shape[1], rgbs[0].shape[0]))
        with torch.inference_mode():
            images = network_images(rgbs, plan, self.predictor.device)
            if depth is None:
                depth = self.predictor.depth(images, plan.network_input, seen)[:, 0].float().cpu().numpy()
                if seen is not None:
                    depth = np.where(seen[0, 0].numpy() > 0, depth, np.float32(0))
        net_cam = plan.network_input
        assert isinstance(net_cam, CylindricalCamera)
        if not np.isfinite(depth).all():
            raise CylsfmError(f"{self.name}: the network's depth is not finite")
        pictures = (images.permute(0, 2, 3, 1).clamp(0, 1) * 255).round().byte().cpu().numpy()
        note = "relative: the network's units (one unknown scale)"
        return [
            Scene(image, d, net_cam, "network units", note, source=(rgb, plan.camera))
            for image, d, rgb in zip(pictures, depth, rgbs, strict=True)
        ]
