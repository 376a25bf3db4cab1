"""Each frame's depth for :func:`cylsfm.odometry`: where it comes from (the depth network, or a dataset's
ground truth for testing the refinement on its own), the depth files written beside the trajectory, and
the scale each file is written in.

The network's depth has one unknown unit that wanders from frame to frame by several percent. A ride that
the bundle adjustment posed has sparse points in the trajectory's one unit, so each frame's depth is
brought to them (:func:`point_factors`): the depth files, the trajectory and the points then share one
scale along the whole ride by construction.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..data.format import load_depth, save_depth
from ..data.geometry import RideGeometry
from ..geometry import Camera
from ..geometry.photometric import resize_depth
from ..model import Predictor

__all__ = [
    "MIN_POINTS",
    "RAW_DEPTH",
    "DepthScale",
    "DepthSource",
    "depth_writer",
    "point_factors",
    "remove_raw_depth",
    "scale_depth_files",
]

#: Where depth maps wait in network units until their scale is known (metres, the adjusted points).
RAW_DEPTH = ".odometry-depth"

#: A frame's depth is brought to the adjusted points where it sees at least this many of them.
MIN_POINTS = 20


class DepthSource:
    """The depth ``[B,1,h,w]`` of network-size frames ``[B,3,H,W]`` in the view the networks see (all of
    a full panorama; the centred crop of a model of crops).

    Args:
        predictor: the networks (their depth, unless ``files`` are given).
        camera: the camera of the network-size frames.
        mask: ``[1,1,H,W]`` (1: the scene is seen), given to the depth network; ``None``: every pixel.
        files: ground-truth depth files of the ride's frames, by index (then the depth is in metres).
    """

    def __init__(
        self,
        predictor: Predictor,
        camera: Camera,
        mask: Tensor | None = None,
        files: list[Path] | None = None,
    ) -> None:
        self.predictor, self.camera, self.files = predictor, camera, files
        self.masked = {"mask": mask} if mask is not None else {}
        self.window = predictor.window(camera)

    @property
    def truth(self) -> bool:
        """Whether the depth is the ground truth's (metres), not the depth network's (network units)."""
        return self.files is not None

    @property
    def unit(self) -> str:
        """The depth's unit in words."""
        return "metres (ground-truth depth)" if self.truth else "network units"

    def __call__(self, indices: list[int], images: Tensor) -> Tensor:
        """The depth of frames ``indices`` (their network-size images ``images [B,3,H,W]``) ``[B,1,h,w]``."""
        if self.files is not None:
            return torch.stack([self._true(i) for i in indices])
        return self.network(images)

    def network(self, images: Tensor) -> Tensor:
        """The depth network's depth ``[B,1,h,w]`` (network units) of ``images [B,3,H,W]``."""
        with torch.inference_mode():
            return self.predictor.depth(images, self.camera, **self.masked).float().clone()

    def _true(self, i: int) -> Tensor:
        """Frame ``i``'s ground-truth depth ``[1,h,w]`` at the network's size, in the view it sees."""
        assert self.files is not None
        depth = torch.from_numpy(load_depth(self.files[i]))[None, None]
        d = resize_depth(depth, (self.camera.height, self.camera.width))
        return (d if self.window is None else d[..., self.window[0] : self.window[1]])[0]


def depth_writer(folder: Path, stems: list[str]) -> Callable[[list[int], Tensor], None]:
    """A sink for the tracker's depth: frame ``i``'s ``[1,h,w]`` as ``FOLDER/STEM.npy`` (``stems[i]``)."""
    folder.mkdir(parents=True, exist_ok=True)

    def write(indices: list[int], depth: Tensor) -> None:
        for i, d in zip(indices, depth, strict=True):
            save_depth(folder / f"{stems[i]}.npy", d[0].cpu().numpy())

    return write


def scale_depth_files(raw: Path, folder: Path, stems: list[str], scale: float | np.ndarray) -> None:
    """``FOLDER/STEM.npy`` = ``RAW/STEM.npy`` times ``scale`` (one factor, or one ``[M]`` per frame) for
    every frame (atomic writes: idempotent, so a run killed halfway writes them all again)."""
    folder.mkdir(parents=True, exist_ok=True)
    factors = np.broadcast_to(np.asarray(scale, dtype=np.float32), (len(stems),))
    for stem, factor in zip(stems, factors, strict=True):
        save_depth(folder / f"{stem}.npy", load_depth(raw / f"{stem}.npy") * factor)


@dataclass(frozen=True)
class DepthScale:
    """Each frame's depth factor from the network's unit to the ride's adjusted points.

    Attributes:
        factors: ``float64 [M]`` what frame ``j``'s network depth is multiplied by.
        points: ``int64 [M]`` the points each factor was measured on (below :data:`MIN_POINTS`: the frame's
            factor is interpolated from the frames around it).
    """

    factors: np.ndarray
    points: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """For ``odometry.json``: how the factors were found, their spread, every frame's factor."""
        measured = self.points >= MIN_POINTS
        f = self.factors
        return {
            "method": f"each frame's depth brought to the adjusted points it sees (weighted median of the log "
            f"ratio, at least {MIN_POINTS} points; other frames interpolated)",
            "frames_measured": int(measured.sum()),
            "points_median": float(np.median(self.points)) if len(f) else 0.0,
            "factor_median": float(np.median(f)) if len(f) else 1.0,
            "factor_cv": float(f.std() / f.mean()) if len(f) else 0.0,
            "factors": [round(float(v), 6) for v in f],
        }


def point_factors(
    geometry: RideGeometry, view: Camera, depth: Callable[[int], np.ndarray], base: float = 1.0
) -> DepthScale:
    """The factor that brings each frame's network depth to the ride's adjusted points.

    Every point a frame saw is projected by ``view`` (the camera of the network's depth maps, centred
    as the frame's: a full panorama at the network's size); where it falls, the map ``depth(j)``
    ``[h,w]`` (network units, 0 unknown) is compared with the point's depth in ``view``'s sense. The
    factor is ``exp`` of the median of ``log(point / map)``, each point weighted by ``1 / sigma^2`` (its
    parallax's uncertainty, :class:`~cylsfm.data.geometry.RideGeometry`, no smaller than the frame's
    median sigma, so that a few points never decide alone). A frame that sees fewer than
    :data:`MIN_POINTS` points gets the factor interpolated (in log) between the measured frames around
    it, or the nearest one's at either end; with no frame measured, every frame gets ``base``.
    """
    m = len(geometry.c2w)
    grid = torch.from_numpy(geometry.local).T[None, :, :, None]
    uv = view.project(grid)[0, :, :, 0].T.numpy()
    seen = view.depth_of(grid)[0, 0, :, 0].numpy()
    ok = view.projectable(grid)[0, 0, :, 0].numpy() & (seen > 0)
    logs = np.full(m, np.nan)
    counts = np.zeros(m, np.int64)
    for j in range(m):
        lo, hi = np.searchsorted(geometry.frame, [j, j + 1])
        if hi - lo < MIN_POINTS:
            continue
        ratio, weight = _ratios(depth(j), view, uv[lo:hi], seen[lo:hi], geometry.sigma[lo:hi], ok[lo:hi])
        counts[j] = len(ratio)
        if len(ratio) >= MIN_POINTS:
            logs[j] = _weighted_median(ratio, weight)
    known = np.nonzero(np.isfinite(logs))[0]
    if not len(known):
        return DepthScale(np.full(m, float(base)), counts)
    factors = np.exp(np.interp(np.arange(m), known, logs[known]))
    return DepthScale(factors, counts)


def _ratios(
    depth: np.ndarray, view: Camera, uv: np.ndarray, seen: np.ndarray, sigma: np.ndarray, ok: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``log(point / map)`` ``[K]`` and the weights ``1 / sigma^2`` of the points that fall on a known
    pixel of the map ``[h,w]`` (the nearest pixel; a full panorama's columns wrap), ``sigma`` raised to
    the frame's median: the better-triangulated half weighs alike, the rest less."""
    h, w = depth.shape
    col = np.round(uv[:, 0]).astype(np.int64)
    row = np.round(uv[:, 1]).astype(np.int64)
    if view.wraps:
        col %= w
    ok = ok & (row >= 0) & (row < h) & (col >= 0) & (col < w)
    net = np.zeros(len(uv))
    net[ok] = depth[row[ok], col[ok]]
    ok &= net > 0
    sigma = sigma[ok]
    floor = np.median(sigma) if len(sigma) else 0.0  # the better half weighs alike: no few points decide
    return np.log(seen[ok] / net[ok]), 1.0 / np.maximum(sigma, floor) ** 2


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value below which half the weight lies (``values``, ``weights`` ``[K]``, K > 0)."""
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def remove_raw_depth(raw: Path) -> None:
    """Remove the maps in network units once the scaled ones are all written."""
    shutil.rmtree(raw, ignore_errors=True)
