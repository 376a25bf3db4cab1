"""``cylsfm predict`` on a video: frames per second with the network at batch 1 and at batch 8, in fp32 and
with the network in bf16 (where the CPU has it natively), depth files only (no pictures). The video is a
synthetic ride (``cylsfm synth`` frames at twice the network's size, encoded with PyAV); the model is the
default recipe's networks at the network's size, untrained (the work does not depend on the weights).
Each run is its own process, one after the other in one invocation.

    python benchmarks/bench_predict.py                  # 120 frames, network 512x128
    python benchmarks/bench_predict.py --frames 40 --size 256x64
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from fractions import Fraction
from pathlib import Path


def _setup(work: Path, frames: int, w: int, h: int) -> tuple[Path, Path]:
    import numpy as np
    from PIL import Image

    from cylsfm.data.synth import generate_dataset
    from cylsfm.data.video import VideoWriter
    from cylsfm.model import untrained_checkpoint

    data = work / "ride"
    generate_dataset(
        data, sequences=1, frames=frames, width=2 * w, height=2 * h, seed=0, progress=False, overwrite=True
    )
    video = work / "ride.mp4"
    writer = VideoWriter(video, Fraction(10))
    for f in sorted((data / "seq_000" / "images").glob("*.png")):
        writer.write(np.asarray(Image.open(f).convert("RGB")))
    writer.close()
    return video, untrained_checkpoint(work / "model.pt", w, h)


def worker(video: str, ckpt: str, out: str, batch: int, amp: bool) -> dict:
    from cylsfm.model import Predictor
    from cylsfm.predict import predict

    predictor = Predictor.from_checkpoint(ckpt, "cpu", amp=amp)
    t0 = time.perf_counter()
    summary = predict(predictor, [video], out, batch_size=batch, png=False, progress=False)
    seconds = time.perf_counter() - t0
    frames = sum(1 for _ in Path(out).rglob("*.npy"))
    del summary
    return {"seconds": seconds, "frames": frames, "networks": "bf16" if predictor.dtype else "fp32"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--size", default="512x128", help="the network's WxH (the video is twice as large)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(*json.loads(args.worker))))
        return
    import torch

    w, h = (int(v) for v in args.size.lower().split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        video, ckpt = _setup(Path(tmp), args.frames, w, h)
        print(
            f"{args.frames} frames of {2 * w}x{2 * h} video, network {w}x{h}, {torch.get_num_threads()} threads"
        )
        print("| batch | networks | frames/s | / batch 1, fp32 |")
        print("|---|---|---|---|")
        base = None
        for batch in (1, 8):
            for amp in (False, True):
                out = Path(tmp) / f"out-{batch}-{amp}"
                job = json.dumps([str(video), str(ckpt), str(out), batch, amp])
                res = subprocess.run(
                    [sys.executable, __file__, "--worker", job], capture_output=True, text=True, check=True
                )
                r = json.loads(res.stdout.strip().splitlines()[-1])
                if amp and r["networks"] == "fp32":
                    continue  # no native bf16 on this CPU
                fps = r["frames"] / r["seconds"]
                base = base or fps
                print(f"| {batch} | {r['networks']} | {fps:.1f} | {base / fps:.2f}x the time |")


if __name__ == "__main__":
    main()
