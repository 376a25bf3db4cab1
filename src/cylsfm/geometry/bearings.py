"""Keypoints as bearings: the unit direction in the camera's axes (x right, y down, z forward) of a pixel
of any camera model, and back. A bundle adjustment of panoramas measures directions, not pixels: a
bearing is defined all around the camera, across the seam and behind it.

>>> import torch
>>> from cylsfm.geometry import CylindricalCamera
>>> cam = CylindricalCamera.full(512, 128)  # cx = 256, cy = 63.5
>>> b = pixel_bearings(cam, torch.tensor([[256.0, 63.5], [384.0, 63.5]], dtype=torch.float64))
>>> b.round(decimals=6).tolist()  # the centre column looks ahead, a quarter turn right along +x
[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
>>> bearing_pixels(cam, b).round(decimals=9).tolist()
[[256.0, 63.5], [384.0, 63.5]]
"""

from __future__ import annotations

from torch import Tensor

from ..errors import check_shape
from .cameras import Camera

__all__ = ["bearing_pixels", "pixel_bearings"]


def pixel_bearings(camera: Camera, uv: Tensor) -> Tensor:
    """Unit bearings ``[N,3]`` of pixel coordinates ``uv [N,2]`` (``u`` right, ``v`` down; integer values
    are pixel centres) of ``camera``."""
    check_shape(uv, "N,2", "uv")
    rays = camera.rays(uv.T[None])[0].T  # [N,3]
    return rays / rays.norm(dim=1, keepdim=True)


def bearing_pixels(camera: Camera, bearings: Tensor) -> Tensor:
    """The pixel coordinates ``[N,2]`` where directions ``bearings [N,3]`` (any length) land in ``camera``."""
    check_shape(bearings, "N,3", "bearings")
    return camera.project(bearings.T[None, :, :, None])[0, :, :, 0].T
