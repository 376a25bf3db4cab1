"""An occluder fixed to the camera: what a helmet camera sees of its rider, or a roof camera of its car.

The same pixels of every frame show the same textured object, which moves with the camera and so looks
like a scene standing still: the test case of the masks (``prepare --mask``, ``train --mask``, odometry's
``--mask``). Two shapes: ``helmet``, a band along the bottom of the image, taller behind the camera (the
rider's head and shoulders) than ahead, and a mounting pole rising on the right (about 18% of a panorama);
``roof``, a car's roof filling the bottom rows all around, wider ahead and behind (about 35%). The texture
is fixed stripes and blots, strong enough that an alignment that uses these pixels is pulled towards no
motion.
"""

from __future__ import annotations

import numpy as np

__all__ = ["OCCLUDERS", "occluder_mask", "occluder_texture"]

#: The occluders ``cylsfm synth --occluder`` knows.
OCCLUDERS = ("none", "helmet", "roof")


def occluder_mask(width: int, height: int, kind: str = "helmet") -> np.ndarray:
    """``bool [H,W]``: True on the occluder ``kind`` (``"helmet"`` or ``"roof"``) of a ``width`` x
    ``height`` image (a full panorama's columns: the centre column looks ahead, the edge columns behind)."""
    u = (np.arange(width) + 0.5) / width  # 0.5 ahead
    v = (np.arange(height) + 0.5) / height  # 0 top, 1 bottom
    ahead = np.cos(2 * np.pi * (u - 0.5))  # 1 ahead, -1 behind
    if kind == "roof":  # lowest at the sides (the roof's edges are nearest there)
        top = 0.62 + 0.06 * np.cos(4 * np.pi * (u - 0.5))
        return v[:, None] >= top[None, :]
    if kind != "helmet":
        raise ValueError(f"unknown occluder {kind!r}; one of {', '.join(OCCLUDERS[1:])}")
    top = 0.84 + 0.07 * ahead  # the band's upper edge: 0.91 ahead, 0.77 behind
    band = v[:, None] >= top[None, :]
    pole_centre = 0.5 + 100 / 360  # 100 degrees to the right
    pole = (np.abs(u - pole_centre) < 0.02)[None, :] & (v >= 0.45)[:, None]
    return band | pole


def occluder_texture(width: int, height: int, seed: int = 7) -> np.ndarray:
    """``uint8 [H,W,3]``: the occluder's fixed texture (diagonal stripes and blots on dark blue-grey)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    stripes = 0.5 + 0.5 * np.sign(np.sin((xx + yy) * (2 * np.pi / max(6.0, width / 40))))
    blots = rng.random((max(2, height // 4), max(2, width // 8)))
    blots = np.kron(blots, np.ones((4, 8)))[:height, :width]
    blots = np.pad(blots, ((0, height - blots.shape[0]), (0, width - blots.shape[1])), mode="edge")
    grey = 0.25 + 0.35 * stripes + 0.3 * blots
    colour = np.stack((0.55 * grey, 0.6 * grey, 0.75 * grey), -1)
    return np.clip(colour * 255 + 0.5, 0, 255).astype(np.uint8)
