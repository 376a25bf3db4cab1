"""Diagnostic: can a photometric loss teach the pose network to turn?

Fine-tunes only the pose network of a checkpoint (its depth network frozen) with one variant of the loss,
on batches of which half are turning samples (ground-truth yaw above 2 degrees), and every 50 steps prints
how the predicted yaw of the 48 sharpest turns of the test split follows the truth: the least-squares slope
through the origin (1 = right, 0 = no rotation learned) and the correlation.

    python experiments/pose_finetune.py CHECKPOINT VARIANT [--steps 300] [--threads 1] [--data ROOT]

VARIANT is a comma-separated list applied to the ``improved`` loss: ``nofull`` (each scale at its own
resolution), ``noautomask``, ``nominrep`` (sum over sources), ``nossim`` (L1 only), ``paper`` (the
``paper-synthia`` loss instead), ``rot10`` (rotation outputs multiplied by 10), ``auxW`` (add W times
the paper's plain photometric term); ``improved`` alone changes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch

from cylsfm.data.dataset import SampleOptions, SequenceDataset, build_index, camera_of
from cylsfm.geometry import mat_to_pose_vec, pose_vec_to_mat
from cylsfm.losses import LossConfig, view_synthesis_loss
from cylsfm.model import load_models
from cylsfm.model.config import preset


def loss_config(variant: str) -> LossConfig:
    cfg = preset("improved").loss
    for v in variant.split(","):
        if v == "nofull":
            cfg = dataclasses.replace(cfg, full_resolution=False)
        elif v == "paper":
            cfg = preset("paper-synthia").loss
        elif v == "noautomask":
            cfg = dataclasses.replace(cfg, automask=False)
        elif v == "nominrep":
            cfg = dataclasses.replace(cfg, min_reprojection=False)
        elif v == "nossim":
            cfg = dataclasses.replace(cfg, ssim_weight=0.0)
        elif v not in ("improved", "rot10") and not v.startswith("aux"):
            raise SystemExit(f"unknown variant {v!r}")
    return cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("variant")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--data", default="experiments/out/data")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    models = load_models(args.checkpoint)
    cfg = loss_config(args.variant)
    variants = args.variant.split(",")
    aux_weight = sum(float(v[3:]) for v in variants if v.startswith("aux"))
    print(cfg, flush=True)
    options = SampleOptions(size=(256, 64))
    train = SequenceDataset(build_index(args.data, "train", seq_length=3), options)
    test = SequenceDataset(build_index(args.data, "test", seq_length=3), options)

    def yaws(ds: SequenceDataset) -> np.ndarray:  # ground-truth yaw to the first source, radians
        return np.array([float(mat_to_pose_vec(ds[i]["pose_gt"])[1, 4]) for i in range(len(ds))])

    def predict(pose_net: torch.nn.Module, tgt: torch.Tensor, src: torch.Tensor) -> tuple:
        vec, masks = pose_net(tgt, src)
        if "rot10" in variants:
            vec = torch.cat([vec[..., :3], vec[..., 3:] * 10], -1)
        return vec, masks

    rng = np.random.default_rng(0)
    y_train, y_test = yaws(train), yaws(test)
    turns = np.flatnonzero(np.abs(y_train) > np.radians(2))
    everything = np.arange(len(train))
    sharpest = np.argsort(-np.abs(y_test))[:48]

    def evaluate() -> tuple[float, float]:
        models.pose_net.eval()
        with torch.no_grad():
            b = [test[i] for i in sharpest]
            vec, _ = predict(
                models.pose_net, torch.stack([x["target"] for x in b]), torch.stack([x["sources"] for x in b])
            )
        pred, gt = vec[:, 1, 4].numpy(), y_test[sharpest]
        return float(np.dot(pred, gt) / np.dot(gt, gt)), float(np.corrcoef(pred, gt)[0, 1])

    print(args.variant, "turn fraction", len(turns) / len(train), "before slope/corr", evaluate(), flush=True)
    opt = torch.optim.Adam(models.pose_net.parameters(), lr=2e-4)
    models.disp_net.eval()
    plain = dataclasses.replace(preset("paper-synthia").loss, smooth_weight=0.0)
    for step in range(args.steps):
        models.pose_net.train()
        idx = [int(rng.choice(turns)) if k < 2 else int(rng.choice(everything)) for k in range(4)]
        b = [train[i] for i in idx]
        tgt, src = torch.stack([x["target"] for x in b]), torch.stack([x["sources"] for x in b])
        with torch.no_grad():
            disps = models.disp_net(tgt)
        vec, masks = predict(models.pose_net, tgt, src)
        cam = camera_of(b[0])
        out = view_synthesis_loss(tgt, src, disps, pose_vec_to_mat(vec), cam, cfg, explainability=masks)
        loss = out.total
        if aux_weight:
            aux = view_synthesis_loss(tgt, src, disps, pose_vec_to_mat(vec), cam, plain)
            loss = loss + aux_weight * aux.terms["photometric"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (step + 1) % 50 == 0:
            print(step + 1, round(out.terms["photometric"].item(), 4), "slope/corr", evaluate(), flush=True)


if __name__ == "__main__":
    main()
