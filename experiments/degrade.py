"""A dataset's panoramas degraded as a consumer 360-degree camera records them, into a new dataset (the
depth, poses, camera and splits copied unchanged), for the robustness rows of RESULTS.md:

- exposure drift: each ride's gain wanders slowly over the ride (+-25%, in linear light) with a little
  flicker from frame to frame (1%);
- vignetting of two back-to-back fisheye lenses (their axes at azimuth 0 and 180 degrees): the light falls
  off as the square of the angle from the nearer lens's axis, 35% at 90 degrees;
- stitching seams where the two lenses meet (azimuth +-90 degrees): one lens's half 6% brighter than the
  other, and a band 3 columns wide at each seam shifted down by one row (the stitcher's misalignment);
- an occluder fixed to the camera (the mount below it): the bottom sixth of the rows over 60 degrees of
  azimuth behind the camera painted dark grey with some texture, its ``mask.png`` written (white: scene);
- JPEG at quality 60 (the frames stay PNG files of the decoded JPEG, so that every name is kept).

Usage: python experiments/degrade.py DATA OUT [--seed S] [--without NAME ...] (NAME one of exposure,
vignetting, seams, occluder, jpeg).
"""

from __future__ import annotations

import argparse
import io
import math
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from cylsfm.data.format import list_images

NAMES = ("exposure", "vignetting", "seams", "occluder", "jpeg")


def _gains(frames: int, rng: np.random.Generator) -> np.ndarray:
    phase, period = rng.uniform(0, 2 * math.pi), rng.uniform(60, 120)
    t = np.arange(frames)
    slow = 0.25 * np.sin(2 * math.pi * t / period + phase)
    return np.exp(slow + 0.01 * rng.standard_normal(frames))


def _azimuth(w: int) -> np.ndarray:
    """The azimuth of each column ``[W]`` in radians (cylindrical full panorama: cx = W/2)."""
    return (np.arange(w) - w / 2) * (2 * math.pi / w)


def _occluder(h: int, w: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``(mask [H,W] bool: the occluder, paint [H,W,3] float)``."""
    az = np.abs(np.angle(np.exp(1j * (_azimuth(w) - math.pi))))  # distance from straight behind
    rows = np.arange(h) >= h - max(h // 6, 1)
    mask = rows[:, None] & (az[None, :] <= math.radians(30))
    paint = 0.18 + 0.04 * rng.standard_normal((h, w, 1)).repeat(3, 2)
    return mask, np.clip(paint, 0, 1)


def degrade(image: np.ndarray, gain: float, use: set[str], occluder) -> np.ndarray:
    """``uint8 [H,W,3]`` -> degraded ``uint8 [H,W,3]``."""
    w = image.shape[1]
    lin = (image.astype(np.float64) / 255.0) ** 2.2
    az = _azimuth(w)
    if "vignetting" in use:
        off = np.minimum(np.abs(az), math.pi - np.abs(az))  # angle from the nearer lens's axis
        lin = lin * (1 - 0.35 * (off / (math.pi / 2)) ** 2)[None, :, None]
    if "seams" in use:
        lin = lin * np.where(np.abs(az) < math.pi / 2, 1.06, 1.0)[None, :, None]
        for seam in (-math.pi / 2, math.pi / 2):
            cols = np.nonzero(np.abs(az - seam) <= 1.5 * (2 * math.pi / w))[0]
            lin[1:, cols] = lin[:-1, cols].copy()
    if "exposure" in use:
        lin = lin * gain
    out = np.clip(lin, 0, 1) ** (1 / 2.2)
    if "occluder" in use:
        mask, paint = occluder
        out[mask] = paint[mask]
    out = (out * 255.0 + 0.5).astype(np.uint8)
    if "jpeg" in use:
        buf = io.BytesIO()
        Image.fromarray(out).save(buf, format="JPEG", quality=60)
        out = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--without", nargs="*", default=[], choices=NAMES)
    args = ap.parse_args()
    use = set(NAMES) - set(args.without)
    if args.out.exists():
        raise SystemExit(f"{args.out}: exists already")
    shutil.copytree(args.data, args.out, ignore=shutil.ignore_patterns("images"))
    seqs = sorted(p for p in args.data.iterdir() if (p / "camera.json").is_file())
    for k, seq in enumerate(seqs):
        rng = np.random.default_rng([args.seed, k])
        images = list_images(seq)
        gains = _gains(len(images), rng)
        first = np.asarray(Image.open(images[0]).convert("RGB"))
        occluder = _occluder(*first.shape[:2], rng)
        dest = args.out / seq.name / "images"
        dest.mkdir(parents=True)
        for image, gain in zip(images, gains, strict=True):
            pixels = np.asarray(Image.open(image).convert("RGB"))
            Image.fromarray(degrade(pixels, float(gain), use, occluder)).save(dest / f"{image.stem}.png")
        if "occluder" in use:
            Image.fromarray(np.where(occluder[0], 0, 255).astype(np.uint8)).save(
                args.out / seq.name / "mask.png"
            )
        print(f"{seq.name}: {len(images)} frames")


if __name__ == "__main__":
    main()
