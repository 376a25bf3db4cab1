"""Throughput of the training data loader (``SequenceDataset`` + ``DataLoader``).

Writes a dataset to a temporary directory with :class:`cylsfm.data.SequenceWriter` (by default 4 sequences
x 60 frames of textured 512x128 panoramas with depth and poses), then measures samples/s of a
``DataLoader`` (batch 4, shuffled, default augmentation: mirror + colour jitter, 3-frame snippets) for
several worker counts, at the stored 512x128 and resized to 256x64 (area interpolation). Each figure is
the median over several full passes, after one warm-up pass (workers are persistent, so worker start-up
is not counted).

    python benchmarks/bench_loader.py                  # the table of BENCHMARKS.md
    python benchmarks/bench_loader.py --passes 3 --workers 0 2
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch.utils.data import DataLoader

from cylsfm import CylindricalCamera
from cylsfm.data import AugmentConfig, SampleOptions, SequenceDataset, SequenceWriter, build_index


def _smooth_noise(rng: np.random.Generator, width: int, height: int, cells: tuple[int, int]) -> np.ndarray:
    """``float32 [height, width, 3]`` smooth random texture from a coarse grid upsampled bicubically."""
    coarse = rng.random((cells[1], cells[0], 3)).astype(np.float32)
    chans = [
        np.asarray(
            Image.fromarray(coarse[..., c], mode="F").resize((width, height), Image.Resampling.BICUBIC)
        )
        for c in range(3)
    ]
    return np.stack(chans, -1)


def write_dataset(root: Path, sequences: int, frames: int, width: int, height: int) -> None:
    """A textured panorama per sequence, rotated and brightened a little from frame to frame."""
    cam = CylindricalCamera.full(width, height)
    for s in range(sequences):
        rng = np.random.default_rng(s)
        texture = (
            0.55 * _smooth_noise(rng, width, height, (16, 4))
            + 0.30 * _smooth_noise(rng, width, height, (128, 32))
            + 0.15 * _smooth_noise(rng, width, height, (width // 2, height // 2))
        )
        depth = 2.0 + 8.0 * _smooth_noise(rng, width, height, (8, 2))[..., 0]
        writer = SequenceWriter(root / f"seq_{s:03d}", cam)
        poses = np.tile(np.eye(4), (frames, 1, 1))
        for i in range(frames):
            img = np.roll(texture, 2 * i, axis=1) * (0.95 + 0.1 * rng.random())
            img = img + rng.normal(0, 0.01, img.shape)
            writer.add_frame((np.clip(img, 0, 1) * 255).round().astype(np.uint8), np.roll(depth, 2 * i, 1))
            poses[i, 2, 3] = 0.1 * i
        writer.finish(poses)


def measure(ds: SequenceDataset, workers: int, batch: int, passes: int) -> float:
    """Median samples/s over ``passes`` full shuffled passes (after one warm-up pass)."""
    loader = DataLoader(
        ds, batch_size=batch, shuffle=True, num_workers=workers, persistent_workers=workers > 0
    )
    rates = []
    for p in range(passes + 1):
        t0 = time.perf_counter()
        n = 0
        for b in loader:
            n += b["target"].shape[0]
        dt = time.perf_counter() - t0
        if p:  # pass 0 warms up (worker start, page cache)
            rates.append(n / dt)
    del loader
    return statistics.median(rates)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sequences", type=int, default=4)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--passes", type=int, default=5)
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2, 4])
    parser.add_argument("--sizes", nargs="+", default=["512x128", "256x64"], help="loader output sizes")
    parser.add_argument(
        "--modes",
        nargs="+",
        default=["decode", "decode-no-gt", "cache-no-gt"],
        choices=["decode", "decode-no-gt", "cache-no-gt"],
        help="decode: every frame decoded per sample, with ground truth (the evaluation's loader); "
        "decode-no-gt: without depth and poses (what training needs); cache-no-gt: frames decoded once "
        "(the trainer's default)",
    )
    args = parser.parse_args()
    # more workers than cores is measured on purpose
    warnings.filterwarnings("ignore", message="This DataLoader will create")
    width, height = 512, 128
    with tempfile.TemporaryDirectory(prefix="cylsfm_bench_loader_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        write_dataset(root, args.sequences, args.frames, width, height)
        write_s = time.perf_counter() - t0
        mib = sum(p.stat().st_size for p in root.rglob("*") if p.is_file()) / 2**20
        print(
            f"dataset: {args.sequences} sequences x {args.frames} frames of {width}x{height} PNG + depth + poses, "
            f"{mib:.1f} MiB, written in {write_s:.1f} s"
        )
        print(
            f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
            f"{torch.get_num_threads()} torch threads in the main process"
        )
        print(f"loader: batch {args.batch}, shuffled, AugmentConfig() (mirror + colour jitter), seq_length 3")
        print(f"median of {args.passes} passes after a warm-up pass\n")
        print("| output size | frames | workers | samples/s | ms/sample |")
        print("|---|---|---|---|---|")
        index = build_index(root)  # every configuration loads the same snippets
        for spec in args.sizes:
            w, h = (int(v) for v in spec.split("x"))
            for mode in args.modes:
                options = SampleOptions(
                    size=None if (w, h) == (width, height) else (w, h),
                    augment=AugmentConfig(),
                    ground_truth=mode == "decode",
                    cache=mode == "cache-no-gt",
                )
                ds = SequenceDataset(index, options)
                for workers in args.workers:
                    rate = measure(ds, workers, args.batch, args.passes)
                    print(f"| {w}x{h} | {mode} | {workers} | {rate:.0f} | {1000 / rate:.2f} |", flush=True)


if __name__ == "__main__":
    main()
