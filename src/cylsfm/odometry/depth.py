"""Each frame's depth for :func:`cylsfm.odometry`: where it comes from (the depth network, or a dataset's
ground truth for testing the refinement on its own) and the depth files written beside the trajectory."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..data.format import load_depth, save_depth
from ..geometry import Camera
from ..geometry.photometric import resize_depth
from ..model import Predictor

__all__ = ["RAW_DEPTH", "DepthSource", "depth_writer", "remove_raw_depth", "scale_depth_files"]

#: Where depth maps wait in network units until the scale to metres is known.
RAW_DEPTH = ".odometry-depth"


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


def scale_depth_files(raw: Path, folder: Path, stems: list[str], scale: float) -> None:
    """``FOLDER/STEM.npy`` = ``RAW/STEM.npy`` times ``scale`` for every frame (atomic writes: idempotent,
    so a run killed halfway writes them all again)."""
    folder.mkdir(parents=True, exist_ok=True)
    for stem in stems:
        save_depth(folder / f"{stem}.npy", load_depth(raw / f"{stem}.npy") * np.float32(scale))


def remove_raw_depth(raw: Path) -> None:
    """Remove the maps in network units once the scaled ones are all written."""
    shutil.rmtree(raw, ignore_errors=True)
