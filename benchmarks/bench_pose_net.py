"""Time the pose network's forward + backward pass for each pose model, as built by the presets.

The pose models differ in cost: the default recipe's antisymmetric pair network runs its encoder on
(target, source) and (source, target) for every source (4 passes of 6 channels for 3-frame snippets)
where the paper's one-pass network runs once on 9 channels; the compass adds two FFTs per pair. All
models are timed in one process, one after the other, so that their ratio is measured on the same
machine state.

    python benchmarks/bench_pose_net.py                       # 256x64, batch 4 (the demo's)
    python benchmarks/bench_pose_net.py --size 512x128 --reps 9
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from cylsfm.model import apply_overrides, build_models, preset

MODELS = {
    "default (pair network, equivariant, compass)": [],
    "default without the compass": ["model.compass=false"],
    "one-pass network + compass (the default before)": ["model.antisymmetric=false", "model.pose_head=mean"],
    "one-pass network (paper's pose network)": [
        "model.antisymmetric=false",
        "model.pose_head=mean",
        "model.compass=false",
    ],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="256x64", help="WxH")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--reps", type=int, default=12)
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(args.batch, 3, height, width, generator=gen)
    sources = torch.rand(args.batch, 2, 3, height, width, generator=gen)
    print(
        f"pose network forward + backward, batch {args.batch}, {width}x{height}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads; median of {args.reps}"
    )
    base = None
    for name, overrides in MODELS.items():
        cfg = apply_overrides(preset("default"), [f"data.width={width}", f"data.height={height}", *overrides])
        _, pose = build_models(cfg)
        pose.train()
        times = []
        for i in range(args.reps + 2):
            t0 = time.perf_counter()
            out, _ = pose(target, sources)
            out.sum().backward()
            if i >= 2:  # two warm-up passes
                times.append(time.perf_counter() - t0)
        ms = 1000 * statistics.median(times)
        base = base or ms
        print(f"  {name:50s} {ms:7.1f} ms  ({ms / base:.2f}x the default)")


if __name__ == "__main__":
    main()
