"""Camera models: cylindrical panoramas and ordinary pinhole views.

Conventions (see ``docs/conventions.md``):

* camera axes: x right, y down, z forward;
* pixel coordinates ``(u, v)``: ``u`` along the width, ``v`` along the height, integer values at pixel
  centres, so an image of width ``W`` spans ``u`` in ``[-0.5, W - 0.5]``;
* cylindrical projection: ``theta = atan2(x, z)``, ``h = y / sqrt(x^2 + z^2)``, ``u = fx * theta + cx``,
  ``v = fy * h + cy``; a full 360 degree panorama of width ``W`` has ``fx = W / (2 pi)`` and ``cx = W / 2``;
* cylindrical depth is ``d = sqrt(x^2 + z^2)`` (horizontal distance from the vertical axis) and
  ``unproject = d * (sin theta, h, cos theta)``;
* pinhole depth is ``z``;
* equirectangular: ``u = fx * theta + cx``, ``v = fy * asin(y / |p|) + cy``, depth is the range ``|p|``.

Every camera holds scalar intrinsics (floats) or, for a batch of different cameras, tensors of shape
``[B]``. All methods are differentiable in the points / depths and work on any device and float dtype.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor

from ..atomic import atomic_write_bytes
from ..errors import CylsfmError, ShapeError, check_shape, reading

Param = float | Tensor

__all__ = [
    "Camera",
    "CameraError",
    "CylindricalCamera",
    "EquirectangularCamera",
    "PinholeCamera",
    "load_camera",
]

# Relative tolerance with which ``fx * 2 pi`` must equal the width for a camera to count as a full 360
# degree panorama.
_FULL_TURN_RTOL = 1e-4
_EPS = 1e-6


class CameraError(CylsfmError, ValueError):
    """A camera description is invalid (bad file, missing or non-positive parameter ...)."""


def _bcast(p: Param, ref: Tensor) -> Param:
    """Return ``p`` ready to broadcast against a ``[B, H, W]`` tensor (floats stay floats)."""
    if isinstance(p, Tensor):
        return p.to(device=ref.device, dtype=ref.dtype).reshape(-1, 1, 1)
    return p


def _azimuth(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(theta, r, y)`` of points ``[B,3,H,W]``, each ``[B,H,W]``: the azimuth ``atan2(x, z)`` (radians), the
    horizontal distance ``sqrt(x^2 + z^2)`` (at least a tiny epsilon) and the height ``y``.

    Points on the vertical axis have no azimuth: they are nudged to ``(0, eps)`` so that the value and the
    gradient stay finite (their image row is then far outside the image, and ``projectable`` flags them).
    """
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    r2 = x * x + z * z
    small = r2 < _EPS * _EPS
    z = torch.where(small, torch.full_like(z, _EPS), z)
    x = torch.where(small, torch.zeros_like(x), x)
    return torch.atan2(x, z), torch.sqrt(torch.clamp(r2, min=_EPS * _EPS)), y


@dataclass(frozen=True)
class Camera:
    """Common part of all camera models: image size in pixels and the four intrinsics (pixels)."""

    width: int
    height: int
    fx: Param
    cx: Param
    fy: Param
    cy: Param

    model: ClassVar[str] = ""

    def __post_init__(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height:
            raise CameraError(f"image size must be integers, got {self.width}x{self.height}")
        if self.width < 1 or self.height < 1:
            raise CameraError(f"image size must be positive, got {self.width}x{self.height}")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            ok = bool((value > 0).all()) if isinstance(value, Tensor) else value > 0
            if not ok:
                raise CameraError(f"{name} must be positive, got {value}")
        for name in ("fx", "cx", "fy", "cy"):
            value = getattr(self, name)
            finite = bool(torch.isfinite(value).all()) if isinstance(value, Tensor) else math.isfinite(value)
            if not finite:
                raise CameraError(f"{name} must be finite, got {value}")

    # ------------------------------------------------------------------ the intrinsics' linear map
    def _to_pixels(self, a: Tensor, b: Tensor) -> Tensor:
        """``(u, v) = (fx a + cx, fy b + cy)`` for the model's angles or slopes ``a, b [B,...]`` -> ``[B,2,...]``."""
        return torch.stack(
            (_bcast(self.fx, a) * a + _bcast(self.cx, a), _bcast(self.fy, b) * b + _bcast(self.cy, b)), 1
        )

    def _from_pixels(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """The inverse of :meth:`_to_pixels`: ``uv [B,2,...]`` -> ``(a, b)``, each ``[B,...]``."""
        u, v = uv[:, 0], uv[:, 1]
        return (u - _bcast(self.cx, u)) / _bcast(self.fx, u), (v - _bcast(self.cy, v)) / _bcast(self.fy, v)

    # ------------------------------------------------------------------ geometry (per subclass)
    def project(self, points: Tensor) -> Tensor:
        """Project camera-frame points ``[B,3,H,W]`` (metres) to pixel coordinates ``[B,2,H,W]`` (u, v)."""
        raise NotImplementedError

    def unproject(self, depth: Tensor) -> Tensor:
        """Lift a depth map ``[B,1,H,W]`` (metres, this model's depth) to camera points ``[B,3,H,W]``.

        Every model's rays are scaled so that multiplying by its own depth gives the point.
        """
        check_shape(depth, "B,1,H,W", "depth")
        b, _, hgt, wid = depth.shape
        if (wid, hgt) != self.size:
            raise ShapeError(f"depth is {wid}x{hgt} but the camera is {self.width}x{self.height}")
        return self.rays(self.pixel_grid(b, depth.device, depth.dtype)) * depth

    def depth_of(self, points: Tensor) -> Tensor:
        """This model's depth of camera-frame points ``[B,3,...]`` -> ``[B,1,...]`` (metres)."""
        raise NotImplementedError

    def projectable(self, points: Tensor) -> Tensor:
        """Boolean ``[B,1,H,W]``: the points ``[B,3,H,W]`` have a well-defined projection."""
        raise NotImplementedError

    def rays(self, uv: Tensor) -> Tensor:
        """Points at unit depth ``[B,3,...]`` for pixel coordinates ``uv [B,2,...]``."""
        raise NotImplementedError

    # ------------------------------------------------------------------ shared
    @property
    def wraps(self) -> bool:
        """True when the image covers a full turn horizontally and its columns wrap around."""
        return False

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return (int(self.width), int(self.height))

    def _full_turn(self) -> bool:
        """``fx * 2 pi == width`` (relative tolerance 1e-4): the columns span exactly one turn of azimuth."""
        fx = self.fx
        if isinstance(fx, Tensor):
            return bool(((fx * 2 * math.pi - self.width).abs() <= _FULL_TURN_RTOL * self.width).all())
        return abs(fx * 2 * math.pi - self.width) <= _FULL_TURN_RTOL * self.width

    def pixel_grid(
        self, batch: int = 1, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
    ) -> Tensor:
        """Pixel-centre coordinates ``[batch,2,H,W]``: channel 0 is ``u`` (column), channel 1 is ``v`` (row)."""
        v, u = torch.meshgrid(
            torch.arange(self.height, device=device, dtype=dtype),
            torch.arange(self.width, device=device, dtype=dtype),
            indexing="ij",
        )
        return torch.stack((u, v), 0).unsqueeze(0).expand(batch, -1, -1, -1)

    def resized(self, width: int, height: int) -> Camera:
        """The camera of this image resampled to ``width x height`` pixels.

        Pixel centres move as in an area/bilinear resize (``align_corners=False``):
        ``u' = (u + 0.5) * width / W - 0.5``, so ``cx' = (cx + 0.5) * sx - 0.5``. A full panorama stays a
        full panorama (``fx' * 2 pi == width``); note that after a 2x downsampling ``cx'`` is
        ``width / 2 - 0.25``, not ``width / 2``, because the new pixel centres sit between the old ones.
        """
        if width < 1 or height < 1:
            raise CameraError(f"resized size must be positive, got {width}x{height}")
        sx = width / self.width
        sy = height / self.height
        return replace(
            self,
            width=int(width),
            height=int(height),
            fx=self.fx * sx,
            cx=(self.cx + 0.5) * sx - 0.5,
            fy=self.fy * sy,
            cy=(self.cy + 0.5) * sy - 0.5,
        )

    def scaled(self, factor: float) -> Camera:
        """The camera of this image resized by ``factor`` (e.g. ``0.5`` for the next network scale).

        ``width * factor`` and ``height * factor`` are rounded to the nearest integer; the intrinsics are
        scaled by the exact ratio of the new to the old size (see :meth:`resized`).
        """
        if factor <= 0:
            raise CameraError(f"scale factor must be positive, got {factor}")
        return self.resized(max(1, round(self.width * factor)), max(1, round(self.height * factor)))

    def pyramid(self, sizes: list[tuple[int, int]]) -> list[Camera]:
        """Cameras for a list of ``(width, height)`` image sizes (e.g. those of the network's outputs)."""
        return [self if (w, h) == self.size else self.resized(w, h) for (w, h) in sizes]

    def to_dict(self) -> dict[str, Any]:
        """The ``camera.json`` dictionary (scalar cameras only)."""
        out: dict[str, Any] = {"model": self.model}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Tensor):
                if value.numel() != 1:
                    raise CameraError("a batched camera cannot be written to JSON; index it first")
                value = float(value)
            out[f.name] = int(value) if f.name in ("width", "height") else float(value)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "camera") -> Camera:
        """Build a camera from a ``camera.json`` dictionary; ``source`` names the file in errors."""
        if not isinstance(data, dict):
            raise CameraError(f"{source}: expected a JSON object, got {type(data).__name__}")
        model = data.get("model", cls.model or None)
        target = _MODELS.get(str(model)) if model is not None else None
        if target is None:
            raise CameraError(f"{source}: unknown camera model {model!r} (expected one of {sorted(_MODELS)})")
        if cls.model and target is not cls:
            raise CameraError(f"{source}: camera model is {model!r}, expected {cls.model!r}")
        values: dict[str, Any] = {}
        for key in ("width", "height", "fx", "cx", "fy", "cy"):
            if key not in data:
                raise CameraError(f"{source}: missing key {key!r}")
            raw = data[key]
            if isinstance(raw, bool) or not isinstance(raw, int | float):
                raise CameraError(f"{source}: {key} must be a number, got {raw!r}")
            if key in ("width", "height"):
                if not math.isfinite(raw) or int(raw) != raw:
                    raise CameraError(f"{source}: {key} must be an integer, got {raw!r}")
                raw = int(raw)
            values[key] = raw
        try:
            return target(**values)
        except CameraError as exc:
            raise CameraError(f"{source}: {exc}") from None

    def to_json(self, path: str | os.PathLike[str]) -> None:
        """Write ``camera.json`` atomically (temporary file + rename)."""
        atomic_write_bytes(path, (json.dumps(self.to_dict(), indent=2) + "\n").encode())

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> Camera:
        """Read ``camera.json``; errors name the file and the problem."""
        path = Path(path)
        with reading(path, CameraError):
            if not path.exists():
                raise CameraError(f"{path}: camera file not found")
            text = path.read_text()
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CameraError(f"{path}: not valid JSON ({exc})") from None
        return cls.from_dict(data, source=str(path))

    def index(self, i: int) -> Camera:
        """The ``i``-th camera of a batched camera (a scalar camera returns itself)."""

        def pick(p: Param) -> Param:
            return float(p.reshape(-1)[i]) if isinstance(p, Tensor) else p

        return replace(self, fx=pick(self.fx), cx=pick(self.cx), fy=pick(self.fy), cy=pick(self.cy))

    @staticmethod
    def stack(cameras: list[Camera]) -> Camera:
        """Batch cameras of one model and one image size into a camera with ``[B]`` tensor intrinsics."""
        if not cameras:
            raise CameraError("cannot stack an empty list of cameras")
        first = cameras[0]
        for cam in cameras[1:]:
            if type(cam) is not type(first) or cam.size != first.size:
                raise CameraError("stacked cameras must share model and image size")

        def col(name: str) -> Tensor:
            return torch.tensor([float(getattr(c, name)) for c in cameras], dtype=torch.float64)

        return replace(first, fx=col("fx"), cx=col("cx"), fy=col("fy"), cy=col("cy"))


@dataclass(frozen=True)
class CylindricalCamera(Camera):
    """A cylindrical panorama: azimuth along the width, height on the unit cylinder along the height.

    ``u = fx * atan2(x, z) + cx``, ``v = fy * y / sqrt(x^2 + z^2) + cy``; depth is the horizontal
    distance ``sqrt(x^2 + z^2)``. A full 360 degree panorama has ``fx = width / (2 pi)``; then
    :attr:`wraps` is true and column ``width`` is column ``0`` again.
    """

    model: ClassVar[str] = "cylindrical"

    @property
    def wraps(self) -> bool:
        return self._full_turn()

    @classmethod
    def full(cls, width: int, height: int, vfov_h: float = 1.0) -> CylindricalCamera:
        """A full 360 degree panorama whose rows span ``h`` in ``[-vfov_h, vfov_h]`` (edge to edge).

        ``fx = width / (2 pi)``, ``cx = width / 2``, ``fy = height / (2 vfov_h)``, ``cy = (height - 1) / 2``.
        The default ``vfov_h = 1`` is +-45 degrees of elevation, as in the paper's Headcam preparation.

        >>> cam = CylindricalCamera.full(512, 128)
        >>> cam.wraps, cam.hfov_deg
        (True, 360.0)
        >>> point = torch.tensor([1.0, 0.0, 1.0]).reshape(1, 3, 1, 1)  # 45 degrees to the right, at eye level
        >>> cam.project(point).flatten()  # u = fx * pi/4 + cx = 320, v = cy
        tensor([320.0000,  63.5000])
        >>> round(cam.depth_of(point).item(), 5)  # cylindrical depth: the horizontal distance
        1.41421
        """
        return cls(
            width=width,
            height=height,
            fx=width / (2 * math.pi),
            cx=width / 2,
            fy=height / (2 * vfov_h),
            cy=(height - 1) / 2,
        )

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view in degrees (360 for a full panorama)."""
        return math.degrees(self.width / float(self.fx if not isinstance(self.fx, Tensor) else self.fx[0]))

    def project(self, points: Tensor) -> Tensor:
        check_shape(points, "B,3,H,W", "points")
        theta, r, y = _azimuth(points)
        return self._to_pixels(theta, y / r)

    def rays(self, uv: Tensor) -> Tensor:
        theta, h = self._from_pixels(uv)
        return torch.stack((torch.sin(theta), h, torch.cos(theta)), 1)

    def unproject(self, depth: Tensor) -> Tensor:
        """Cylindrical depth ``[B,1,H,W]`` -> camera points ``[B,3,H,W]`` = ``d (sin theta, h, cos theta)``.

        >>> cam = CylindricalCamera.full(4, 2)
        >>> points = cam.unproject(torch.full((1, 1, 2, 4), 2.0))
        >>> points[0, :, 0, 2]  # the centre column looks straight ahead; row 0 is above the horizon
        tensor([ 0., -1.,  2.])
        >>> torch.allclose(cam.depth_of(points), torch.tensor(2.0))
        True
        """
        return super().unproject(depth)

    def depth_of(self, points: Tensor) -> Tensor:
        return torch.sqrt(points[:, 0:1] ** 2 + points[:, 2:3] ** 2)

    def projectable(self, points: Tensor) -> Tensor:
        return (points[:, 0:1] ** 2 + points[:, 2:3] ** 2) > _EPS * _EPS

    def crop_window(self, hfov_deg: float) -> tuple[int, int]:
        """Columns ``[x0, x1)`` of the centred ``hfov_deg`` crop (centred on the forward direction)."""
        if not 0 < hfov_deg <= 360:
            raise CameraError(f"crop field of view must be in (0, 360] degrees, got {hfov_deg}")
        fx = float(self.fx) if not isinstance(self.fx, Tensor) else float(self.fx.reshape(-1)[0])
        cx = float(self.cx) if not isinstance(self.cx, Tensor) else float(self.cx.reshape(-1)[0])
        n = round(math.radians(hfov_deg) * fx)
        if n > self.width:
            raise CameraError(f"a {hfov_deg} degree crop needs {n} columns, the image has {self.width}")
        if n < 1:
            raise CameraError(f"a {hfov_deg} degree crop of a {self.width}-pixel image is empty")
        x0 = math.floor(cx - n / 2 + 0.5)
        x0 = min(max(x0, 0), self.width - n)
        return x0, x0 + n

    def crop(self, hfov_deg: float) -> CylindricalCamera:
        """The camera of the centred ``hfov_deg`` crop of this panorama (see :meth:`crop_window`).

        A crop narrower than 360 degrees does not wrap. Apply the same columns to images with
        ``image[..., x0:x1]``.
        """
        x0, x1 = self.crop_window(hfov_deg)
        return replace(self, width=x1 - x0, cx=self.cx - x0)


@dataclass(frozen=True)
class PinholeCamera(Camera):
    """An ordinary perspective camera: ``u = fx x / z + cx``, ``v = fy y / z + cy``; depth is ``z``."""

    model: ClassVar[str] = "pinhole"

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> PinholeCamera:
        """A centred pinhole camera with square pixels and the given horizontal field of view."""
        f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
        return cls(width=width, height=height, fx=f, cx=(width - 1) / 2, fy=f, cy=(height - 1) / 2)

    def project(self, points: Tensor) -> Tensor:
        check_shape(points, "B,3,H,W", "points")
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        z = torch.where(z.abs() < _EPS, torch.full_like(z, _EPS), z)
        return self._to_pixels(x / z, y / z)

    def rays(self, uv: Tensor) -> Tensor:
        x, y = self._from_pixels(uv)
        return torch.stack((x, y, torch.ones_like(x)), 1)

    def depth_of(self, points: Tensor) -> Tensor:
        return points[:, 2:3]

    def projectable(self, points: Tensor) -> Tensor:
        return points[:, 2:3] > _EPS


@dataclass(frozen=True)
class EquirectangularCamera(Camera):
    """An equirectangular (latitude-longitude) panorama, the usual output of 360-degree cameras.

    ``u = fx * theta + cx``, ``v = fy * phi + cy`` with ``theta = atan2(x, z)`` and the elevation
    ``phi = asin(y / |p|)`` (positive downwards); depth is the range ``|p|``. The full sphere of a
    ``W x H`` image has ``fx = W / (2 pi)``, ``cx = W / 2 - 1/2``, ``fy = H / pi``, ``cy = H / 2 - 1/2``
    (:meth:`full`), i.e. ``x_e = W (theta / 2 pi + 1/2) - 1/2`` and ``y_e = H (phi / pi + 1/2) - 1/2``.
    """

    model: ClassVar[str] = "equirectangular"

    @property
    def wraps(self) -> bool:
        return self._full_turn()

    @classmethod
    def full(cls, width: int, height: int) -> EquirectangularCamera:
        """The whole sphere in a ``width x height`` image (usually ``width == 2 * height``)."""
        return cls(
            width=width,
            height=height,
            fx=width / (2 * math.pi),
            cx=width / 2 - 0.5,
            fy=height / math.pi,
            cy=height / 2 - 0.5,
        )

    def project(self, points: Tensor) -> Tensor:
        check_shape(points, "B,3,H,W", "points")
        theta, r, y = _azimuth(points)
        return self._to_pixels(theta, torch.atan2(y, r))

    def rays(self, uv: Tensor) -> Tensor:
        """Unit-range directions (``|ray| = 1``) for pixel coordinates ``uv [B,2,...]``."""
        theta, phi = self._from_pixels(uv)
        c = torch.cos(phi)
        return torch.stack((c * torch.sin(theta), torch.sin(phi), c * torch.cos(theta)), 1)

    def depth_of(self, points: Tensor) -> Tensor:
        # not torch.linalg.vector_norm(dim=1): on the CPU its reduction across channels of a [B,3,H,W]
        # map runs about 200x slower than these element-wise operations (torch 2.13)
        return points[:, 0:3].square().sum(1, keepdim=True).sqrt()

    def projectable(self, points: Tensor) -> Tensor:
        return (points[:, 0:1] ** 2 + points[:, 2:3] ** 2) > _EPS * _EPS


_MODELS: dict[str, type[Camera]] = {
    "cylindrical": CylindricalCamera,
    "pinhole": PinholeCamera,
    "equirectangular": EquirectangularCamera,
}


def load_camera(path: str | os.PathLike[str]) -> Camera:
    """Read a ``camera.json`` of any supported model (its ``"model"`` key picks the class)."""
    return Camera.from_json(path)
