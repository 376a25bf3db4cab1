"""Feasibility: plane sweep over a ride's neighbours with given poses; coverage and accuracy of the
confident pixels against the ground truth. Usage: sweep_check.py DATA RIDE [WxH] [poses.txt]"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from cylsfm.data.format import list_images
from cylsfm.data.io import load_depth, load_image, read_tum
from cylsfm.geometry import CylindricalCamera
from cylsfm.geometry.warp import sample_image, transform_points

torch.set_num_threads(2)
K1, K2 = int(os.environ.get("K1", 1)), int(os.environ.get("K2", 2))


def box(x, r, wrap=True):
    k = 2 * r + 1
    if wrap:
        x = torch.cat((x[..., -r:], x, x[..., :r]), -1)
        x = F.pad(x, (0, 0, r, r), mode="replicate")
    else:
        x = F.pad(x, (r, r, r, r), mode="replicate")
    return F.avg_pool2d(x, k, stride=1)


def sweep(tgt, srcs, T, cam, depths, r=2):
    """tgt [1,1,H,W] grey, srcs [S,1,H,W], T [S,4,4] tgt->src, depths [D] -> cost [D,H,W] (1 - zncc)."""
    mu_t = box(tgt, r)
    sd_t = (box(tgt * tgt, r) - mu_t**2).clamp(min=0).sqrt()
    costs = []
    for d in depths:
        dm = torch.full_like(tgt, float(d))
        pts = cam.unproject(dm)
        per = []
        for s in range(len(srcs)):
            p = transform_points(T[s : s + 1], pts)
            uv = cam.project(p)
            w, valid = sample_image(srcs[s : s + 1], uv, True)
            mu_w = box(w, r)
            sd_w = (box(w * w, r) - mu_w**2).clamp(min=0).sqrt()
            cov = box(w * tgt, r) - mu_w * mu_t
            zncc = cov / (sd_w * sd_t + 1e-4)
            c = (1 - zncc).clamp(0, 2)
            c = torch.where(valid, c, torch.full_like(c, 2.0))
            per.append(c)
        per = torch.cat(per, 1)[0]  # [S,H,W]
        best2 = per.sort(0).values[: max(1, len(srcs) // 2)].mean(0)
        costs.append(best2)
    return torch.stack(costs), sd_t[0, 0]


def main():
    data, ride = Path(sys.argv[1]), sys.argv[2]
    w, h = map(int, (sys.argv[3] if len(sys.argv) > 3 else "256x64").split("x"))
    seq = data / ride
    images = list_images(seq)
    posefile = sys.argv[4] if len(sys.argv) > 4 else seq / "poses.txt"
    _, c2w = read_tum(posefile)
    c2w = torch.from_numpy(c2w)
    gt_c2w = torch.from_numpy(read_tum(seq / "poses.txt")[1])
    cam = CylindricalCamera.full(w, h)  # vfov as the dataset's? use camera.json
    import json

    cj = json.loads((seq / "camera.json").read_text())
    from cylsfm.geometry import Camera

    cam = Camera.from_dict(cj).resized(w, h)
    depth_files = sorted((seq / "depth").iterdir())
    steps = (gt_c2w[1:, :3, 3] - gt_c2w[:-1, :3, 3]).norm(dim=1).median()
    est_steps = (c2w[1:, :3, 3] - c2w[:-1, :3, 3]).norm(dim=1).median()
    scale = float(steps / est_steps)
    print("scale est->gt", scale)
    nd = 48
    inv = torch.linspace(1 / 0.5, 1 / 100.0, nd, dtype=torch.float64) / scale
    depths = 1 / inv
    res = []
    t0 = time.time()
    for t in range(K2, len(images) - K2, 10):

        def grey(i):
            return (
                torch.from_numpy(load_image(images[i], (w, h)).astype(np.float32))
                .permute(2, 0, 1)
                .mean(0, keepdim=True)[None]
                / 255.0
            )

        srcs_i = [t - K2, t - K1, t + K1, t + K2]
        tgt = grey(t)
        srcs = torch.cat([grey(i) for i in srcs_i])
        T = torch.stack([torch.linalg.inv(c2w[i]) @ c2w[t] for i in srcs_i]).float()
        cost, sd = sweep(tgt, srcs, T, cam, depths.float())
        best, arg = cost.min(0)
        # second best outside +-2 hypotheses
        idx = torch.arange(nd)[:, None, None]
        far = (idx - arg[None]).abs() > 2
        second = torch.where(far, cost, torch.full_like(cost, 9)).min(0).values
        a = arg.clamp(1, nd - 2)
        c0, c1, c2 = (cost.gather(0, (a + k)[None])[0] for k in (-1, 0, 1))
        den = (c0 - 2 * c1 + c2).clamp(min=1e-6)
        off = (0.5 * (c0 - c2) / den).clamp(-0.5, 0.5)
        invs = inv.float()
        ia = invs[a] + off * (invs[1] - invs[0])
        d = (1 / ia) * scale
        gt = torch.from_numpy(load_depth(depth_files[t], (w, h)))
        ok_gt = (gt > 1e-3) & (gt < 80)
        row = []
        for bt, mg, sdt in ((0.3, 0.15, 0.02), (0.2, 0.3, 0.04), (0.1, 0.5, 0.05)):
            conf = (best < bt) & (second - best > mg) & (sd > sdt) & (arg > 0) & (arg < nd - 1)
            m = conf & ok_gt
            rel = ((d - gt).abs() / gt)[m]
            row += [
                m.float().mean().item(),
                rel.median().item() if len(rel) else float("nan"),
                rel.mean().item() if len(rel) else float("nan"),
                (rel < 0.1).float().mean().item() if len(rel) else float("nan"),
            ]
        res.append(row)
    res = np.array(res)
    print("frames", len(res), "time/frame", (time.time() - t0) / len(res))
    for k in range(3):
        cov, med, mean, within = np.nanmean(res, 0)[4 * k : 4 * k + 4]
        print(f"coverage {cov:.3f}  median rel {med:.3f}  mean rel {mean:.3f}  within10% {within:.3f}")


if __name__ == "__main__":
    main()
