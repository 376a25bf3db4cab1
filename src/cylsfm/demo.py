"""``cylsfm demo``: a self-contained run on built-in synthetic data.

Current scope (until the street benchmark and the trainer land): render a short panoramic sequence of the
analytic room scene, check that view synthesis with the true depth and poses explains each target frame,
then fit DispNet and PoseExpNet to the sequence by view synthesis for the time budget and report how the
loss fell. Writes ``overview.png`` (input, true depth, predicted depth) and ``summary.json`` to ``out``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from .data.room import make_pose, render_room
from .geometry import CylindricalCamera, inverse_warp, pose_vec_to_mat, relative_pose
from .losses import LossConfig, view_synthesis_loss
from .nn import DispNet, PoseExpNet


def _to_png(rows: list[np.ndarray], path: Path) -> None:
    img = np.concatenate(rows, 0)
    Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)).save(path)


def _colour_depth(depth: np.ndarray) -> np.ndarray:
    """Inverse depth, normalised to [0, 1] and shown in grey-to-orange (near = bright)."""
    inv = 1 / np.maximum(depth, 1e-6)
    inv = (inv - inv.min()) / max(float(inv.max() - inv.min()), 1e-9)
    return np.stack((inv, inv**1.5, inv**3), -1)


def run_demo(
    out: str | Path, minutes: float = 1.0, seed: int = 0, width: int = 256, height: int = 64
) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    cam = CylindricalCamera.full(width, height)
    c2w = [make_pose(0.05 * np.sin(i), 0.0, -1.0 + 0.4 * i, yaw_deg=4 * i) for i in range(7)]
    frames = [render_room(cam, p) for p in c2w]
    images = torch.cat([f[0] for f in frames])  # [N,3,H,W]
    depths = torch.cat([f[1] for f in frames])

    # 1. The geometry: warping each neighbour with the true depth and pose explains the target.
    ratios = []
    for t in range(1, len(frames) - 1):
        for s in (t - 1, t + 1):
            T = relative_pose(c2w[t], c2w[s]).float().unsqueeze(0)
            warped, valid = inverse_warp(images[s : s + 1], depths[t : t + 1], T, cam)
            m = valid.float()
            err_warp = float(((warped - images[t : t + 1]).abs() * m).sum() / m.sum())
            err_none = float(((images[s : s + 1] - images[t : t + 1]).abs() * m).sum() / m.sum())
            ratios.append(err_none / err_warp)
    print(f"true-geometry view synthesis: photometric error {np.median(ratios):.1f}x lower than no warping")

    # 2. Learning: fit the networks to the sequence's 3-frame snippets by view synthesis alone.
    disp_net, pose_net = DispNet(), PoseExpNet(n_sources=2, explainability=False)
    opt = torch.optim.Adam([*disp_net.parameters(), *pose_net.parameters()], lr=2e-4)
    cfg = LossConfig(smooth_weight=0.05, ssim_weight=0.85, min_reprojection=True, automask=True)
    idx = torch.arange(1, len(frames) - 1)
    losses = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < minutes * 60:
        tgt = images[idx]
        src = torch.stack((images[idx - 1], images[idx + 1]), 1)
        disps = disp_net(tgt)
        pose_vec, _ = pose_net(tgt, src)
        loss = view_synthesis_loss(tgt, src, disps, pose_vec_to_mat(pose_vec), cam, cfg).total
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if len(losses) % 20 == 1:
            print(f"step {len(losses):4d}  loss {losses[-1]:.4f}  ({time.monotonic() - t0:.0f} s)")
    disp_net.eval()
    with torch.no_grad():
        pred = 1 / disp_net(images[idx])[0]
    gt = depths[idx]
    scale = gt.flatten(1).median(1).values / pred.flatten(1).median(1).values
    abs_rel = float(((pred * scale.view(-1, 1, 1, 1) - gt).abs() / gt).mean())
    const_rel = float(((gt.flatten(1).median(1).values.view(-1, 1, 1, 1) - gt).abs() / gt).mean())
    summary = {
        "true_geometry_error_ratio": float(np.median(ratios)),
        "steps": len(losses),
        "loss_first": losses[0] if losses else None,
        "loss_last": float(np.mean(losses[-5:])) if losses else None,
        "abs_rel_median_scaled": abs_rel,
        "abs_rel_constant_depth": const_rel,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    k = len(idx) // 2
    _to_png(
        [
            images[idx[k]].permute(1, 2, 0).numpy(),
            _colour_depth(gt[k, 0].numpy()),
            _colour_depth(pred[k, 0].numpy()),
        ],
        out / "overview.png",
    )
    print(json.dumps(summary, indent=2))
    print(f"wrote {out / 'overview.png'} and {out / 'summary.json'}")
    return summary
