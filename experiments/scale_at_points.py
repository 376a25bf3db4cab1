"""Where a ride's depth scale wanders: for each held-out ride that `experiments/ride_scale.sh RUN` ran the
odometry of, the spread (coefficient of variation over the ride) of each frame's depth scale against the
ground truth, measured over all pixels and at the adjusted points only, before and after each frame was
brought to the points; and how well the adjusted points themselves keep one scale. Usage:

    .venv/bin/python experiments/scale_at_points.py experiments/out/plain-256x64-30m
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from cylsfm.data.format import load_depth
from cylsfm.data.geometry import load_geometry
from cylsfm.geometry import CylindricalCamera
from cylsfm.geometry.photometric import resize_depth

DATA = Path("experiments/out/data512")
FRAMES = CylindricalCamera.full(512, 128)  # the benchmark's frames


def cv(values: list[float]) -> float:
    a = np.asarray(values)
    return float(a.std() / a.mean())


def ride(out: Path, seq: str) -> dict[str, float]:
    factors = np.array(json.loads((out / "odometry.json").read_text())["depth_scale"]["factors"])
    stems = sorted(p.stem for p in (out / "depth").glob("*.npy"))
    geo = load_geometry(out, len(stems), FRAMES)
    first = load_depth(out / "depth" / f"{stems[0]}.npy")
    view = CylindricalCamera.full(first.shape[1], first.shape[0])
    grid = torch.from_numpy(geo.local).T[None, :, :, None]
    uv = view.project(grid)[0, :, :, 0].T.numpy()
    seen = view.depth_of(grid)[0, 0, :, 0].numpy()
    pixels, points, adjusted = [], [], []
    for j, stem in enumerate(stems):
        net = load_depth(out / "depth" / f"{stem}.npy") / factors[j]  # the network's own
        gt = torch.from_numpy(load_depth(DATA / seq / "depth" / f"{stem}.npy"))[None, None]
        gt = resize_depth(gt, net.shape)[0, 0].numpy()
        ok = (gt > 1e-3) & (gt < 80) & (net > 0)
        pixels.append(np.median(gt[ok]) / np.median(net[ok]))
        lo, hi = np.searchsorted(geo.frame, [j, j + 1])
        col = np.round(uv[lo:hi, 0]).astype(int) % view.width
        row = np.round(uv[lo:hi, 1]).astype(int)
        inside = (row >= 0) & (row < view.height)
        g, n, d = gt[row[inside], col[inside]], net[row[inside], col[inside]], seen[lo:hi][inside]
        k = (g > 1e-3) & (g < 80) & (n > 0)
        points.append(np.median(g[k] / n[k]))
        adjusted.append(np.median(d[k] / g[k]))
    pixels, points = np.array(pixels), np.array(points)
    return {
        "adjusted points / truth": cv(adjusted),
        "network at the points": cv(points),
        "aligned at the points": cv(points / factors),
        "network over all pixels": cv(pixels),
        "aligned over all pixels": cv(pixels / factors),
        "factors": cv(factors),
    }


def main(run: str) -> None:
    rides = sorted(p.name for p in (Path(run) / "rides").iterdir() if p.is_dir())
    table = {seq: ride(Path(run) / "rides" / seq, seq) for seq in rides}
    print("| spread over the ride | " + " | ".join(rides) + " |")
    print("|---|" + "---|" * len(rides))
    for key in next(iter(table.values())):
        print(f"| {key} | " + " | ".join(f"{table[s][key]:.3f}" for s in rides) + " |")


if __name__ == "__main__":
    main(sys.argv[1])
