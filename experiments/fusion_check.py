"""Feasibility: a ride's depth maps (odometry --refine --depth, in the ride's one scale) fused across
neighbouring frames by the adjusted poses; abs_rel and the ride's scale CV, single frame against fused.
Usage: fusion_check.py DATA RIDE ODOMETRY_OUT [K]"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from cylsfm.data.format import list_images
from cylsfm.data.io import load_depth, read_tum
from cylsfm.geometry import Camera
from cylsfm.geometry.fusion import fuse_depth

torch.set_num_threads(1)


def scores(pred, gt):
    ok = (gt > 1e-3) & (gt < 80) & (pred > 0)
    p, g = pred[ok], gt[ok]
    f = np.median(g) / np.median(p)
    return float(np.mean(np.abs(p * f - g) / g)), f


def main():
    data, ride, odo = Path(sys.argv[1]), sys.argv[2], Path(sys.argv[3])
    k = int(sys.argv[4]) if len(sys.argv) > 4 else 3
    seq = data / ride
    stems = [p.stem for p in list_images(seq)]
    _, c2w = read_tum(odo / "trajectory.txt")
    depths = torch.stack([torch.from_numpy(load_depth(odo / "depth" / f"{s}.npy"))[None] for s in stems])
    h, w = depths.shape[-2:]
    import json

    cam = Camera.from_dict(json.loads((seq / "camera.json").read_text())).resized(w, h)
    fused, spread = fuse_depth(depths, torch.from_numpy(c2w), cam, k)
    gts = [load_depth(seq / "depth" / f"{s}.npy", (w, h)) for s in stems]
    for name, maps in (("single", depths), ("fused", fused)):
        rel, fac = zip(*(scores(maps[i, 0].numpy(), gts[i]) for i in range(len(stems))), strict=True)
        fac = np.array(fac)
        print(f"{name}: abs_rel {np.mean(rel):.4f}  scale CV {fac.std() / fac.mean():.4f}")
    # where the fused is trusted (small spread)
    for thr in (0.02, 0.05, 0.1):
        rs, cov = [], []
        for i in range(len(stems)):
            g = gts[i]
            sel = (spread[i, 0].numpy() < thr) & (g > 1e-3) & (g < 80)
            _, fac = scores(fused[i, 0].numpy(), g)
            p = fused[i, 0].numpy()[sel] * fac
            rs.append(np.mean(np.abs(p - g[sel]) / g[sel]) if sel.any() else np.nan)
            cov.append(sel.mean())
        print(f"spread<{thr}: coverage {np.mean(cov):.3f} abs_rel there {np.nanmean(rs):.4f}")


if __name__ == "__main__":
    main()
