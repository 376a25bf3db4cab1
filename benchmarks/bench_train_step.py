"""Time one training step (DispNet + PoseExpNet + all losses + Adam) and single-image depth inference.

Every configuration runs in its own process so that its peak memory (max RSS) is its own. The achieved
FLOP/s (counted by ``torch.utils.flop_counter``: convolutions and matmuls, forward + backward) is reported
as a fraction of the rate of a plain 3x3 convolution (64 -> 64 channels, channels_last) measured in the
same run, the ceiling that a convolutional network can reach on this machine.

    python benchmarks/bench_train_step.py                   # the table of BENCHMARKS.md
    python benchmarks/bench_train_step.py --steps 5 --sizes 256x64
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import multiprocessing as mp
import platform
import resource
import statistics
import sys
import time

import torch


def median_time(fn, reps: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def conv_reference(threads: int, reps: int) -> dict:
    """Rate of a 3x3 convolution 64->64 channels, channels_last, forward and forward+backward."""
    torch.set_num_threads(threads)
    conv = torch.nn.Conv2d(64, 64, 3, padding=1).to(memory_format=torch.channels_last)
    x = torch.randn(4, 64, 64, 256).contiguous(memory_format=torch.channels_last)
    flops = 2 * 64 * 64 * 9 * x.shape[0] * x.shape[2] * x.shape[3]
    with torch.no_grad():
        t_fwd = median_time(lambda: conv(x), reps)
    xg = x.clone().requires_grad_(True)

    def fwd_bwd() -> None:
        conv.zero_grad(set_to_none=True)
        conv(xg).sum().backward()

    t_fb = median_time(fwd_bwd, reps)
    return {"conv_fwd_gflops": flops / t_fwd / 1e9, "conv_fwd_bwd_gflops": 3 * flops / t_fb / 1e9}


def train_step_bench(
    width: int,
    height: int,
    batch: int,
    threads: int,
    reps: int,
    channels_last: bool,
    cylindrical: bool = True,
    loss: str = "paper",
    adam: str = "cylsfm",
    small_maps: bool = True,
    amp: bool = False,
) -> dict:
    from torch.utils.flop_counter import FlopCounterMode

    from cylsfm.geometry import CylindricalCamera, PinholeCamera, pose_vec_to_mat
    from cylsfm.losses import LossConfig, view_synthesis_loss
    from cylsfm.nn import DispNet, PoseExpNet
    from cylsfm.nn import small_maps as small_maps_module
    from cylsfm.nn.packed import plain_convolutions
    from cylsfm.train.optim import Adam

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    if not small_maps:  # the tiny deepest maps by oneDNN too, as before the matrix-product path
        small_maps_module.MAX_POSITIONS = 0
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    # cylindrical: wrap-aware networks on a full panorama; otherwise the same networks, unwrapped, on a
    # pinhole camera: the SfMLearner baseline, measured in the same run.
    disp_net = DispNet(wrap=cylindrical).to(memory_format=fmt)
    pose_net = PoseExpNet(n_sources=2, explainability=loss == "paper", wrap=cylindrical).to(memory_format=fmt)
    params = list(disp_net.parameters()) + list(pose_net.parameters())
    # cylsfm: the trainer's fused Adam that reads channels-last weights in place; torch: torch's fused Adam
    # (which copies them, the code before); plain: torch's default Adam (SfMLearner's configuration)
    optimizer = Adam if adam == "cylsfm" else torch.optim.Adam
    opt = optimizer(params, lr=2e-4, betas=(0.9, 0.999), fused=True if adam != "plain" else None)
    camera = (
        CylindricalCamera.full(width, height) if cylindrical else PinholeCamera.from_fov(width, height, 90)
    )
    if loss == "paper":  # eq. 1 with every term: L1 + explainability + second-order smoothness
        cfg = LossConfig(smooth_weight=2.0, explain_weight=0.2)
    else:  # the improved loss (presets "improved" and "default")
        from cylsfm.model.config import preset

        cfg = preset("improved").loss
    use_masks = cfg.explain_weight > 0
    target = torch.rand(batch, 3, height, width).contiguous(memory_format=fmt)
    sources = torch.rand(batch, 2, 3, height, width)

    # amp: the networks under bf16 autocast, as cylsfm runs them on a CPU with native bf16 (the trainer's
    # network_precision); the losses, the sampler and the geometry in fp32, on the outputs cast back.
    def networks(x: torch.Tensor) -> list[torch.Tensor]:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            return disp_net(x)

    def step() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            disps = disp_net(target)
            pose_vec, masks = pose_net(target, sources)
        disps, pose_vec = [d.float() for d in disps], pose_vec.float()
        masks = [m.float() for m in masks] if masks is not None else None
        out = view_synthesis_loss(
            target,
            sources,
            disps,
            pose_vec_to_mat(pose_vec),
            camera,
            cfg,
            explainability=masks if use_masks else None,
        )
        opt.zero_grad(set_to_none=True)
        out.total.backward()
        opt.step()

    step()
    counter = FlopCounterMode(display=False)
    with counter:
        step()
    flops = counter.get_total_flops()
    t_step = median_time(step, reps, warmup=1)

    disp_net.eval()
    one = torch.rand(1, 3, height, width).contiguous(memory_format=fmt)
    # SfMLearner's configuration is eager PyTorch: its convolutions lay their weights out at every call
    with torch.inference_mode(), plain_convolutions() if not cylindrical else contextlib.nullcontext():
        t_inf = median_time(lambda: networks(one), max(reps, 10), warmup=2)
        counter = FlopCounterMode(display=False)
        with counter, plain_convolutions():  # the counter knows aten's convolutions, not oneDNN's own
            networks(one)
        inf_flops = counter.get_total_flops()
    return {
        "size": f"{width}x{height}",
        "model": "cylindrical" if cylindrical else "pinhole",
        "loss": loss,
        "batch": batch,
        "channels_last": channels_last,
        "adam": adam,
        "small_maps": small_maps,
        "amp": amp,
        "step_s": t_step,
        "samples_per_s": batch / t_step,
        "step_gflop": flops / 1e9,
        "step_gflops": flops / t_step / 1e9,
        "infer_ms": t_inf * 1e3,
        "infer_gflop": inf_flops / 1e9,
        "infer_gflops": inf_flops / t_inf / 1e9,
        "peak_rss_mib": _peak_rss_mib(),
    }


def _run(job: tuple) -> dict:
    kind, args = job
    return conv_reference(*args) if kind == "conv" else train_step_bench(*args)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="512x128,256x64", help="comma-separated WxH list")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--steps", type=int, default=7, help="timed steps per configuration (median)")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--memory-format", choices=["both", "channels_last", "contiguous"], default="both")
    parser.add_argument("--no-pinhole", action="store_true", help="skip the pinhole (wrap off) baseline rows")
    parser.add_argument(
        "--loss",
        choices=["paper", "improved"],
        default="paper",
        help="paper: eq. 1 with explainability; improved: the loss of presets improved and default (with the paper's one-pass pose network)",
    )
    parser.add_argument(
        "--small-maps",
        choices=["on", "off", "both"],
        default="on",
        help="tiny deepest feature maps as matrix products (cylindrical rows; 'both' adds rows without)",
    )
    parser.add_argument(
        "--amp",
        choices=["on", "off", "both"],
        default="both",
        help="cylindrical rows with the networks in bf16 (on a CPU with native bf16: AVX-512 BF16 or AMX)",
    )
    parser.add_argument(
        "--adam",
        choices=["cylsfm", "torch", "both"],
        default="cylsfm",
        help="cylindrical rows: the trainer's Adam (fused, channels-last weights read in place) or torch's "
        "fused Adam (which copies them); the reference always uses torch's default Adam",
    )
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args(argv)
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes.split(",")]
    formats = {"both": [True, False], "channels_last": [True], "contiguous": [False]}[args.memory_format]
    ctx = mp.get_context("spawn")
    results = {"machine": f"{platform.machine()} {platform.processor()}", "torch": torch.__version__}
    results["threads"] = args.threads
    with ctx.Pool(1, maxtasksperchild=1) as pool:
        results["conv"] = pool.apply(_run, (("conv", (args.threads, 15)),))
        rows = []
        for w, h in sizes:
            for cl in formats:
                choices = itertools.product(
                    {"on": [True], "off": [False], "both": [False, True]}[args.small_maps],
                    {"on": [True], "off": [False], "both": [False, True]}[args.amp],
                    {"cylsfm": ["cylsfm"], "torch": ["torch"], "both": ["torch", "cylsfm"]}[args.adam],
                )
                for small, amp, adam in choices:
                    job = (w, h, args.batch, args.threads, args.steps, cl, True, args.loss, adam, small, amp)
                    rows.append(pool.apply(_run, (("step", job),)))
            if not args.no_pinhole:  # SfMLearner's own configuration: pinhole, contiguous, plain Adam
                job = (w, h, args.batch, args.threads, args.steps, False, False, args.loss, "plain")
                rows.append(pool.apply(_run, (("step", job),)))
        results["conv_after"] = pool.apply(_run, (("conv", (args.threads, 15)),))
    ceiling = max(results["conv"]["conv_fwd_gflops"], results["conv_after"]["conv_fwd_gflops"])
    fb_ceiling = max(results["conv"]["conv_fwd_bwd_gflops"], results["conv_after"]["conv_fwd_bwd_gflops"])
    results["steps"] = rows
    print(
        f"torch {torch.__version__}, {args.threads} threads, batch {args.batch}, {args.loss} loss, median of {args.steps} steps"
    )
    print(
        f"3x3 conv 64->64 channels_last: forward {ceiling:.0f} GFLOP/s, forward+backward {fb_ceiling:.0f} GFLOP/s"
    )
    print(
        "| model | size | memory format | s/step | samples/s | GFLOP/step | GFLOP/s | of conv fwd | of conv f+b "
        "| inference ms | inference GFLOP/s | peak RSS MiB | step / reference |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    reference = {r["size"]: r["step_s"] for r in rows if r["model"] == "pinhole"}
    for r in rows:
        fmt = "channels_last" if r["channels_last"] else "contiguous"
        if r["model"] == "pinhole":
            fmt += ", plain Adam (reference)"
        elif not r["small_maps"]:
            fmt += ", small maps by oneDNN"
        if r["model"] != "pinhole" and r["adam"] == "torch":
            fmt += ", torch's fused Adam"
        if r["amp"]:
            fmt += ", bf16 networks"
        ratio = f"{r['step_s'] / reference[r['size']]:.2f}x" if r["size"] in reference else "-"
        print(
            f"| {r['model']} | {r['size']} | {fmt} | {r['step_s']:.3f} | {r['samples_per_s']:.1f} | {r['step_gflop']:.1f} "
            f"| {r['step_gflops']:.0f} | {r['step_gflops'] / ceiling:.0%} | {r['step_gflops'] / fb_ceiling:.0%} "
            f"| {r['infer_ms']:.1f} | {r['infer_gflops']:.0f} | {r['peak_rss_mib']:.0f} | {ratio} |"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=2)


if __name__ == "__main__":
    sys.exit(main())
