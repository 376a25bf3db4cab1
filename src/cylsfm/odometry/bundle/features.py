"""Sparse features of a ride's frames for the bundle adjustment: SIFT keypoints (OpenCV's; no learned
weights) on each frame at its own resolution, in its own geometry, across the seam of a full panorama
and never on an occluder of the mask.

An occluder fixed to the camera (a helmet, a mount) moves with it: a keypoint on it, or on its outline
against the scene, would be a point that follows the camera. Its pixels are painted one grey before
detecting, so that nothing of it enters a descriptor, and a keypoint is kept only where the occluder is
more than :data:`OUTLINE` times its size away, off the outline the grey makes.

A full panorama's columns wrap: the frame is detected with a band of columns from its other end on each
side (:data:`WRAP`), so that a corner on the seam is found like any other, and each keypoint found in a
band is kept once, at its column in the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["OUTLINE", "UPSAMPLING_SHIFT", "WRAP", "Features", "detect"]

#: Columns taken from the other end on each side of a full panorama before detecting.
WRAP = 24

#: A keypoint is kept only where the occluder is farther than this many times its size (OpenCV's
#: ``KeyPoint.size``, the blob's diameter).
OUTLINE = 1.5

#: Where OpenCV's SIFT puts a keypoint, right of and below the blob's centre, in pixels. Its
#: ``enable_precise_upscale`` has no shift but finds other keypoints, which measured worse at 1024x512
#: (docs/results/bundle-adjustment.md).
UPSAMPLING_SHIFT = 0.25


@dataclass(frozen=True)
class Features:
    """A frame's keypoints ``uv [K,2]`` (pixel coordinates, integer values are pixel centres), their
    SIFT descriptors ``uint8 [K,128]`` (OpenCV's are whole numbers 0-255: a quarter of the memory of a
    ride's float32 ones, which at 1024x512 are 2.8 MB a frame) and the frame's colour at each
    ``uint8 [K,3]``."""

    uv: np.ndarray
    descriptors: np.ndarray
    colours: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)


def detect(
    rgb: np.ndarray, wraps: bool, mask: np.ndarray | None = None, most: int = 2000, contrast: float = 0.04
) -> Features:
    """SIFT keypoints of a frame.

    Args:
        rgb: ``uint8 [H,W,3]``.
        wraps: whether the columns wrap around (a full panorama).
        mask: ``[H,W]``, nonzero where the scene is seen (``None``: everywhere); no keypoint on the rest.
        most: keypoints kept at most (the strongest).
        contrast: SIFT's contrast threshold (OpenCV's ``contrastThreshold``; lower finds more, weaker).
    """
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    h, w = grey.shape
    allowed = np.full((h, w), 255, np.uint8) if mask is None else np.where(mask > 0, 255, 0).astype(np.uint8)
    pad = min(WRAP, w // 2) if wraps else 0
    if pad:
        grey = np.concatenate((grey[:, -pad:], grey, grey[:, :pad]), 1)
        allowed = np.concatenate((allowed[:, -pad:], allowed, allowed[:, :pad]), 1)
    clear = None  # each pixel's distance to the occluder
    if not allowed.all():
        grey = np.where(allowed > 0, grey, 128).astype(np.uint8)  # its content enters no descriptor
        clear = cv2.distanceTransform(allowed, cv2.DIST_L2, 5)
    sift = cv2.SIFT_create(nfeatures=most, contrastThreshold=contrast)
    keypoints, descriptors = sift.detectAndCompute(grey, allowed)
    if descriptors is None or not keypoints:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.uint8), np.zeros((0, 3), np.uint8))
    found = np.array([k.pt for k in keypoints], dtype=np.float64)  # in the padded frame
    keep = np.ones(len(found), dtype=bool)
    if clear is not None:  # off the occluder's outline
        at = np.round(found).astype(np.int64)
        size = np.array([k.size for k in keypoints])
        keep = clear[np.clip(at[:, 1], 0, h - 1), np.clip(at[:, 0], 0, grey.shape[1] - 1)] > OUTLINE * size
    # OpenCV's keypoints are in pixel indices, but its doubled first octave puts every keypoint a quarter pixel
    # right and down (a blob centred on pixel 30 is found at 30.25): a common turn across the columns, but
    # a tilt of every bearing in the rows, taken off here (:data:`UPSAMPLING_SHIFT`)
    uv = found - [pad + UPSAMPLING_SHIFT, UPSAMPLING_SHIFT]
    keep &= (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5)  # a band's keypoints are the frame's own, kept once
    uv = uv[keep]
    col = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, h - 1)
    described = np.clip(np.rint(descriptors[keep]), 0, 255).astype(np.uint8)  # whole numbers already
    return Features(uv, described, np.asarray(rgb)[row, col].astype(np.uint8))
