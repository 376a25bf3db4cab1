"""Diagnostic: does the pose network read the motion from the images, or emit it from its bias?

For test snippets of the benchmark, compares what the pose network predicts for the real snippet with
two inputs of known motion:

- every source replaced by the target itself (a camera standing still: the true motion is zero);
- the two sources swapped (the frame before the target in the second slot, the frame after it in the
  first): a network that reads the motion from the images predicts for each image the same motion as
  before, whichever slot it is in; a network that has learned a motion per slot does not.

    python experiments/static_input.py CHECKPOINT [--data ROOT] [--n 96]

Prints the median translation length (network units) of the real and of the standing-still inputs, and,
for each source image, how its prediction in the other slot compares with its prediction in its own
slot: the median cosine of the translations and the correlation of the yaws (+1: the prediction follows
the image, the motion is read; -1: it follows the slot).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from cylsfm.data.dataset import SampleOptions, SequenceDataset, build_index
from cylsfm.model import load_models


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--data", default="experiments/out/data")
    ap.add_argument("--n", type=int, default=96)
    args = ap.parse_args()
    torch.set_num_threads(1)
    models = load_models(args.checkpoint)
    net = models.pose_net.eval()
    cfg = models.config
    index = build_index(args.data, "test", seq_length=3)
    test = SequenceDataset(index, SampleOptions(size=(cfg.data.width, cfg.data.height)))
    pick = np.linspace(0, len(test) - 1, min(args.n, len(test))).round().astype(int)
    b = [test[int(i)] for i in pick]
    tgt = torch.stack([x["target"] for x in b])  # [B,3,H,W]
    src = torch.stack([x["sources"] for x in b])  # [B,2,3,H,W]
    with torch.no_grad():
        real = net(tgt, src)[0]  # [B,2,6]
        still = net(tgt, tgt[:, None].expand_as(src).contiguous())[0]
        swapped = net(tgt, src.flip(1))[0].flip(1)  # back in image order: [:, 0] is the earlier frame's
    n_real, n_still = real[..., :3].norm(dim=-1), still[..., :3].norm(dim=-1)
    cos = torch.nn.functional.cosine_similarity(real[..., :3], swapped[..., :3], dim=-1)
    yaw_corr = np.corrcoef(real[..., 4].reshape(-1).numpy(), swapped[..., 4].reshape(-1).numpy())[0, 1]
    print(f"{args.checkpoint}: {len(b)} test snippets")
    print(f"  median |t| real snippets         {n_real.median():.4f}")
    print(
        f"  median |t| camera standing still {n_still.median():.4f} ({n_still.median() / n_real.median():.2f}x)"
    )
    print(f"  sources swapped: median cosine of t {cos.median():+.3f}, correlation of yaw {yaw_corr:+.3f}")


if __name__ == "__main__":
    main()
