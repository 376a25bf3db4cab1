"""A ride's own geometry as training targets that need no labels: the poses and sparse points that
:func:`cylsfm.odometry` adjusted over the whole ride (its bundle adjustment), read back from its output
folder (``trajectory.txt`` and ``points.npz``).

Each frame gets the depth of the points it saw, at the keypoints where it saw them, and the relative pose
to any other frame of the ride, all in the ride's one unit. Every depth carries its uncertainty: a point
triangulated from rays ``alpha`` apart is known to about ``sigma_b / sin(alpha)`` of its distance, where
``sigma_b`` is a keypoint's angular noise (:data:`KEYPOINT_PIXELS` pixels), never better than
:data:`DEPTH_FLOOR`.

Where the odometry also wrote each frame's depth in the ride's one scale (``depth/FRAME.npy``, its
``save_depth_maps``), every frame also gets a dense target: its depth fused with that of the
:data:`FUSE_NEIGHBOURS` frames on either side by the adjusted poses
(:func:`~cylsfm.geometry.fusion.fuse_depth`), with the spread of the frames' depths at each pixel.

A folder of such geometry for a dataset holds one odometry output per ride, named as the ride
(``GEOMETRY/seq_003/trajectory.txt`` ...); :class:`~cylsfm.data.SequenceDataset` reads it with
``SampleOptions(geometry=GEOMETRY)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from ..errors import CylsfmError
from ..geometry import Camera, invert
from ..geometry.fusion import fuse_depth
from .io import DatasetError, load_depth, read_tum, resize_nearest
from .points import SparsePoints, read_points

__all__ = [
    "DEPTH_FLOOR",
    "FUSE_NEIGHBOURS",
    "KEYPOINT_PIXELS",
    "TOLERANCE",
    "RideGeometry",
    "load_geometry",
    "ride_geometry",
]

#: A keypoint's noise, in pixels of the ride's own frames (the bundle adjustment's).
KEYPOINT_PIXELS = 0.3

#: An observation is kept where its point projects within this many pixels of its keypoint.
TOLERANCE = 2.0

#: The smallest relative standard deviation a point's depth is given (the network is not asked for more).
DEPTH_FLOOR = 0.01

#: A frame's depth is fused with this many frames on either side (and needs 3 that see a pixel; 5 was
#: the best of 3, 5, 8 and 12 on the benchmark's validation ride, fusing a 30-minute model's depth).
FUSE_NEIGHBOURS = 5


@dataclass(frozen=True)
class RideGeometry:
    """A ride's adjusted geometry, its observations sorted by frame.

    Attributes:
        c2w: ``float64 [M,4,4]`` camera-to-world poses of the ride's frames, in its unit.
        frame: ``int64 [N]`` the frame of each observation (ascending).
        local: ``float64 [N,3]`` its point in that frame's camera axes (x right, y down, z forward), in the
            ride's unit: what any other camera model with the same centre sees of it.
        uv: ``float64 [N,2]`` where that frame saw its point, in the ride's own pixels (``size``).
        depth: ``float64 [N]`` the point's depth from that frame in the camera model's sense
            (``sqrt(x^2 + z^2)`` in the frame's camera axes for a cylinder), in the ride's unit; all positive.
        sigma: ``float64 [N]`` the relative standard deviation of that depth (of its logarithm).
        size: ``(W, H)`` of the ride's own frames; ``wraps``: whether their columns wrap (a full panorama).
        unit: the unit's name (``network units``, or ``m`` with a camera height).
        step: the ride's median step length between consecutive frames, in its unit (positive).
        fused: ``float16 [M,2,h,w]`` each frame's fused depth (0: none) and its spread in log depth, at the
            size of the odometry's depth maps; ``None`` where the odometry wrote none.
    """

    c2w: np.ndarray
    frame: np.ndarray
    local: np.ndarray
    uv: np.ndarray
    depth: np.ndarray
    sigma: np.ndarray
    size: tuple[int, int]
    wraps: bool
    unit: str
    step: float
    fused: np.ndarray | None = None

    def depth_map(self, frame: int, size: tuple[int, int]) -> np.ndarray:
        """``float32 [2,H,W]`` of frame ``frame`` at ``size`` ``(W, H)``: channel 0 the depth of its points
        at their keypoints (0 where none; the nearest where two fall in one pixel), channel 1 their
        relative standard deviation (0 where none). Keypoints are scaled with the frame (pixel centres kept);
        a full panorama's columns wrap, other frames' keypoints outside them are left out."""
        w, h = size
        out = np.zeros((2, h, w), np.float32)
        lo, hi = np.searchsorted(self.frame, [frame, frame + 1])
        if lo == hi:
            return out
        uv, depth, sigma = self.uv[lo:hi], self.depth[lo:hi], self.sigma[lo:hi]
        col = np.round((uv[:, 0] + 0.5) * w / self.size[0] - 0.5).astype(np.int64)
        row = np.round((uv[:, 1] + 0.5) * h / self.size[1] - 0.5).astype(np.int64)
        if self.wraps:
            col %= w
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        pixel = (row * w + col)[inside]
        depth, sigma = depth[inside], sigma[inside]
        order = np.lexsort((depth, pixel))  # by pixel, the nearest first
        pixel, depth, sigma = pixel[order], depth[order], sigma[order]
        first = np.ones(len(pixel), dtype=bool)
        first[1:] = pixel[1:] != pixel[:-1]
        out[0].reshape(-1)[pixel[first]] = depth[first]
        out[1].reshape(-1)[pixel[first]] = sigma[first]
        return out

    def fused_map(self, frame: int, size: tuple[int, int]) -> np.ndarray:
        """``float32 [2,H,W]`` of frame ``frame`` at ``size`` ``(W, H)`` (nearest pixel): its fused depth
        (0: none) and spread; all 0 without fused depth."""
        w, h = size
        if self.fused is None:
            return np.zeros((2, h, w), np.float32)
        maps = self.fused[frame].astype(np.float32)
        if maps.shape[1:] != (h, w):  # both channels in one pass ([H,W,2])
            maps = np.ascontiguousarray(resize_nearest(maps.transpose(1, 2, 0), size).transpose(2, 0, 1))
        return maps

    def targets(self, frame: int, size: tuple[int, int]) -> np.ndarray:
        """``float32 [4,H,W]``: :meth:`depth_map` (the points) and :meth:`fused_map` of frame ``frame``."""
        return np.concatenate((self.depth_map(frame, size), self.fused_map(frame, size)))

    def relative(self, target: int, sources: list[int]) -> np.ndarray:
        """``float64 [S,4,4]`` ``T_target_to_source`` for each source frame (``p_s = T p_t``)."""
        return invert(self.c2w[np.asarray(sources, dtype=np.int64)]) @ self.c2w[target]


def load_geometry(
    folder: str | Path, frames: int, camera: Camera, stems: list[str] | None = None
) -> RideGeometry:
    """The adjusted geometry that :func:`cylsfm.odometry` wrote to ``folder`` for a ride of ``frames``
    frames seen by ``camera`` (at the frames' own size), and, given the frames' names ``stems`` and the
    odometry's depth files (``folder/depth/STEM.npy``, every frame's), each frame's fused depth.

    Only the observations that the geometry explains are kept: the point in front of the frame (its
    camera's depth positive) and projected within :data:`TOLERANCE` pixels of the keypoint (a point
    behind the camera, or a keypoint that does not see it, is no target).

    Raises:
        DatasetError: a file missing or unreadable, a trajectory of another length than the ride, points or
            keypoints that do not fit it, a ride that does not move (naming the file and the problem).
    """
    folder = Path(folder)
    path = folder / "trajectory.txt"
    if not path.is_file():
        raise DatasetError(f"{path}: not found (the ride's cylsfm odometry, with the bundle adjustment)")
    _, c2w = read_tum(path)  # DatasetError naming the file and the line
    if len(c2w) != frames:
        raise DatasetError(f"{path}: {len(c2w)} poses for a ride of {frames} frames")
    try:
        pts = read_points(folder / "points.npz", frames, camera.size)
    except CylsfmError as exc:  # naming the file: a dataset's problem here
        raise DatasetError(str(exc)) from None
    geometry = ride_geometry(c2w, pts, camera)
    if not geometry.step > 0:
        raise DatasetError(f"{path}: the ride does not move (median step {geometry.step})")
    if stems is not None and (folder / "depth").is_dir():
        geometry = replace(geometry, fused=_fused(folder / "depth", stems, c2w, camera))
    return geometry


def _fused(folder: Path, stems: list[str], c2w: np.ndarray, camera: Camera) -> np.ndarray | None:
    """``float16 [M,2,h,w]`` the frames' depth files in ``folder`` fused by the poses ``c2w``; ``None``
    where a frame has no file or the maps are not of the frames' aspect ratio (a model of crops).

    Raises:
        DatasetError: a depth file that cannot be read, or maps of different sizes (naming the file).
    """
    paths = [folder / f"{stem}.npy" for stem in stems]
    if len(paths) != len(c2w) or not all(p.is_file() for p in paths):
        return None
    maps = [load_depth(p) for p in paths]  # DatasetError naming the file
    h, w = maps[0].shape
    for p, m in zip(paths, maps, strict=True):
        if m.shape != (h, w):
            raise DatasetError(f"{p}: a {m.shape[1]}x{m.shape[0]} depth map among {w}x{h} ones")
    if abs(w * camera.height - h * camera.width) > 0.01 * h * camera.width:
        return None
    depths = torch.from_numpy(np.stack(maps))[:, None]
    fused, spread = fuse_depth(depths, torch.from_numpy(c2w), camera.resized(w, h), FUSE_NEIGHBOURS)
    return torch.cat((fused, spread), 1).numpy().astype(np.float16)


def ride_geometry(c2w: np.ndarray, pts: SparsePoints, camera: Camera) -> RideGeometry:
    """The geometry of a ride posed by ``c2w`` ``[M,4,4]`` with the adjusted points and tracks ``pts`` in
    the same world and unit, seen by ``camera`` (at the frames' own size): the observations that it
    explains (as :func:`load_geometry`), by frame."""
    lengths = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)
    step = float(np.median(lengths)) if len(lengths) else 0.0
    x = pts.xyz[pts.point]  # [N,3] world
    centre = c2w[pts.frame, :3, 3]
    local = np.einsum("nji,nj->ni", c2w[pts.frame, :3, :3], x - centre)  # R^T (X - c)
    grid = torch.from_numpy(local).T[None, :, :, None]  # [1,3,N,1], as the camera takes points
    depth = camera.depth_of(grid)[0, 0, :, 0].numpy()
    uv = camera.project(grid)[0, :, :, 0].T.numpy()
    off = np.abs(uv - pts.uv)
    if camera.wraps:
        off[:, 0] = np.minimum(off[:, 0], camera.width - off[:, 0])
    ok = camera.projectable(grid)[0, 0, :, 0].numpy() & (depth > 0) & (off.max(1) <= TOLERANCE)
    ok = np.nonzero(ok)[0]
    sigma = _relative_sigma((x - centre)[ok], pts.point[ok], len(pts.xyz), 1.0 / float(camera.fx))
    order = np.argsort(pts.frame[ok], kind="stable")  # by frame, for depth_map's search
    keep, sigma = ok[order], sigma[order]
    return RideGeometry(
        c2w, pts.frame[keep], local[keep], pts.uv[keep], depth[keep], sigma, camera.size, camera.wraps,
        pts.unit, step,
    )  # fmt: skip


def _relative_sigma(rays: np.ndarray, point: np.ndarray, n_points: int, pixel: float) -> np.ndarray:
    """Each observation's relative depth uncertainty ``[N]`` from its point's parallax: the widest angle
    (at most 90 degrees) between the rays ``[N,3]`` (from the observing frames' centres to the point) and
    the point's first ray, for keypoints of :data:`KEYPOINT_PIXELS` pixels of ``pixel`` radians."""
    unit = rays / np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    first = np.zeros((n_points, 3))
    ids, at = np.unique(point, return_index=True)  # each point's first observation (in file order)
    first[ids] = unit[at]
    cos = np.clip(np.einsum("ni,ni->n", unit, first[point]), 0.0, 1.0)  # beyond 90 degrees: as at 90
    widest = np.ones(n_points)
    np.minimum.at(widest, point, cos)
    sine = np.sqrt(np.maximum(1.0 - widest**2, 1e-12))
    return np.maximum(KEYPOINT_PIXELS * pixel / sine, DEPTH_FLOOR)[point]
