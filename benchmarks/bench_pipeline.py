"""Training's real rate against its isolated step: how much the pipeline (data loading, augmentation,
logging, checkpoints) costs a run of ``cylsfm train``.

For each data setting, in its own process: build the trainer on a generated benchmark (or ``--data``),
time ``--steps`` steps of the real loop (``Trainer.fit``: loader, logging, checkpoints, exactly as
``cylsfm train`` runs), then the isolated step (``Trainer.train_step`` on one batch already in memory) in
the same process. The real rate is taken between the first and the last step after ``--warmup`` steps.

    python benchmarks/bench_pipeline.py                       # 256x64, default recipe
    python benchmarks/bench_pipeline.py --settings cache=false,workers=2 cache=true,workers=0
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _generate(root: Path, width: int, height: int) -> None:
    from cylsfm.data.synth import generate_dataset

    generate_dataset(
        root, sequences=6, frames=100, width=2 * width, height=2 * height, seed=0, splits=True, progress=False
    )


def _run(job: tuple) -> dict:
    data, size, setting, steps, warmup, preset = job
    import torch

    from cylsfm.model.config import apply_overrides
    from cylsfm.model.config import preset as get_preset
    from cylsfm.train.trainer import Trainer

    items = [f"data.root='{data}'", f"data.width={size[0]}", f"data.height={size[1]}", f"max_steps={steps}"]
    items += ["checkpoint_every=0", "device=cpu"] + [f"data.{k}={v}" for k, v in setting.items()]
    cfg = apply_overrides(get_preset(preset), items)
    with tempfile.TemporaryDirectory() as run:
        t_build = time.perf_counter()
        trainer = Trainer(cfg, run)
        t_build = time.perf_counter() - t_build
        stamps: list[float] = []
        step = trainer.train_step

        def timed(batch):
            out = step(batch)
            stamps.append(time.perf_counter())
            return out

        trainer.train_step = timed  # type: ignore[method-assign]
        trainer.fit(progress=False)
        real = (stamps[-1] - stamps[warmup]) / (len(stamps) - 1 - warmup)
        batch = next(iter(trainer._loader()))
        times = []
        for _ in range(max(8, steps // 4)):
            t0 = time.perf_counter()
            step(batch)
            times.append(time.perf_counter() - t0)
        trainer.close()
    isolated = statistics.median(times)
    return {
        "setting": ",".join(f"{k}={v}" for k, v in setting.items()),
        "build_s": t_build,
        "real_s": real,
        "isolated_s": isolated,
        "ratio": isolated / real,
        "threads": torch.get_num_threads(),
    }


def _child(job: tuple, queue) -> None:
    queue.put(_run(job))


def _in_own_process(job: tuple) -> dict:
    """Run one job in a fresh (non-daemonic) process: loader workers may start beneath it."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child, args=(job, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", help="dataset root (default: a generated 6-ride benchmark)")
    parser.add_argument("--size", default="256x64")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--preset", default="default")
    parser.add_argument(
        "--settings",
        nargs="+",
        default=[
            "cache=false,workers=2",
            "cache=false,workers=0",
            "cache=true,workers=0",
            "cache=true,workers=2",
        ],
        help="data settings to compare, each key=value[,key=value]",
    )
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    settings = [dict(item.split("=", 1) for item in s.split(",")) for s in args.settings]
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(args.data) if args.data else Path(tmp) / "data"
        if not args.data:
            _generate(data, *size)
        rows = [_in_own_process((data, size, s, args.steps, args.warmup, args.preset)) for s in settings]
    print(f"{args.size}, preset {args.preset}, {args.steps} steps (rate after {args.warmup}), batch 4")
    print("| data setting | set-up s | real s/step | isolated s/step | isolated / real |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['setting']} | {r['build_s']:.1f} | {r['real_s']:.3f} | {r['isolated_s']:.3f} | {r['ratio']:.0%} |"
        )


if __name__ == "__main__":
    sys.exit(main())
