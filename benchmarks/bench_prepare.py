"""Throughput of ``cylsfm prepare equirect``: decoding a 3840x1920 equirectangular H.264 video against
converting its frames to 2048x512 cylinders (and writing them), per frame.

    python benchmarks/bench_prepare.py                        # 3840x1920 -> 2048x512, 24 frames at 30 fps
    python benchmarks/bench_prepare.py --size 512x128 --frames 12

The video is written first (x264, crf 18, textured content so that decoding does real work). Timed, each
a median over ``--repeats``:

- decode: every frame decoded to RGB (PyAV, threaded, as ``prepare`` reads videos);
- convert: (median of 3x ``--repeats``, after one warm-up call) the resampling of one decoded frame to the cylinder (``Resampler.frames``, the exact separable
  box filter), and the previous supersampled bilinear map for comparison;
- write: one PNG of the output size (``prepare``'s zlib level, on one thread; ``prepare`` writes on two);
- prepare: ``prepare_equirect`` end to end per output frame, every frame and at the paper's 5 fps.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import av
import numpy as np
import torch
from PIL import Image

from cylsfm.data.convert import Resampler, plan_resampling
from cylsfm.data.io import save_png
from cylsfm.data.prepare import EquirectOptions, prepare_equirect
from cylsfm.data.prepare.sequence import PNG_LEVEL
from cylsfm.data.video import video_frames
from cylsfm.geometry import CylindricalCamera, EquirectangularCamera


def _frames(w: int, h: int, n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    coarse = Image.fromarray((rng.random((h // 8, w // 8, 3)) * 255).astype(np.uint8)).resize((w, h))
    base = np.asarray(coarse).astype(np.int16)
    fine = rng.integers(-8, 9, size=(h, w, 1), dtype=np.int16)
    image = np.clip(base + fine, 0, 255).astype(np.uint8)
    return [np.roll(image, 9 * i, axis=1) for i in range(n)]


def _write_video(path: Path, frames: list[np.ndarray], rate: int) -> None:
    h, w = frames[0].shape[:2]
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=rate)
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        stream.options = {"crf": "18", "preset": "veryfast"}
        for f in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode(None):
            out.mux(packet)


def _median(fn, repeats: int, warm: bool = False) -> float:
    if warm:
        fn()  # first call: buffers allocated, pages faulted in
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--input", default="3840x1920", help="equirectangular video size WxH")
    ap.add_argument("--size", default="2048x512", help="output cylinder WxH")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--rate", type=int, default=30, help="the video's frame rate")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    w, h = (int(v) for v in args.input.split("x"))
    ow, oh = (int(v) for v in args.size.split("x"))
    n = args.frames
    frames = _frames(w, h, n)
    with tempfile.TemporaryDirectory() as tmp:
        video = Path(tmp) / "ride.mp4"
        _write_video(video, frames, args.rate)
        rate = av.open(str(video)).streams.video[0].average_rate

        decode = _median(lambda: sum(1 for _ in video_frames(video, rate, None)), args.repeats) / n
        src, dst = EquirectangularCamera.full(w, h), CylindricalCamera.full(ow, oh)
        fast = Resampler(src, dst)
        # the supersampled bilinear map used before the separable filter (same factors as it chose)
        dense = Resampler(src, dst, supersample=plan_resampling(src, dst)[0])

        t_fast = _median(lambda: fast.frames(frames[:1]), 3 * args.repeats, warm=True)
        t_dense = _median(lambda: dense.frames(frames[:1]), 2)
        out_image = fast.frames(frames[:1])[0]
        t_write = _median(lambda: save_png(Path(tmp) / "w.png", out_image, PNG_LEVEL), 3 * args.repeats, True)
        runs = {}
        for fps in (None, 5.0):
            opts = EquirectOptions(size=(ow, oh), fps=fps)
            kept = []

            def run(opts: EquirectOptions = opts, kept: list = kept) -> None:
                reports = prepare_equirect([video], Path(tmp) / "out", opts, overwrite=True, progress=False)
                kept.append(reports[0].written)

            runs[fps] = (_median(run, args.repeats), kept[-1])
    print(
        f"{w}x{h} H.264 -> {ow}x{oh} cylinder, {n} frames at {args.rate} fps, torch threads {torch.get_num_threads()}"
    )
    print(f"decode            {1000 * decode:8.1f} ms/frame")
    print(f"convert           {1000 * t_fast:8.1f} ms/frame  ({t_fast / decode:.2f}x decode)")
    print(f"  dense bilinear  {1000 * t_dense:8.1f} ms/frame  ({t_dense / decode:.2f}x decode, the old map)")
    print(f"write png         {1000 * t_write:8.1f} ms/frame  (zlib level {PNG_LEVEL}, one thread)")
    for fps, (t, written) in runs.items():
        label = "every frame" if fps is None else f"{fps:g} fps"
        print(
            f"prepare, {label:11s} {t:6.2f} s for {written} frames: {1000 * t / written:8.1f} ms per output "
            f"frame, {1000 * t / n:6.1f} ms per video frame ({t / (decode * n):.2f}x decoding alone)"
        )


if __name__ == "__main__":
    main()
