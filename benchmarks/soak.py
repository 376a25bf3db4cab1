"""The soak: the default recipe trained for 20,000 steps at 256x64, every step's loss terms and gradient norm
logged, to show that no value becomes NaN or infinite over a long run.

Resumable: each call trains for at most ``--minutes`` (a run that exists is resumed with ``--resume``, which
continues exactly), so the soak can be spread over several sittings; the report counts every part.

    python benchmarks/soak.py --out soak --minutes 150     # again until it reports "complete"
    python benchmarks/soak.py --out soak --report          # only the report of what is there

The data is the benchmark's (16 rides x 150 frames at 256x64, seed 0, split by sequence), generated once into
``OUT/data``. The report (also written to ``OUT/report.json``): steps, wall-clock time over all parts, the
number of logged rows, how many values were not finite (there must be none: a non-finite loss or gradient
stops training), the largest gradient norm and the loss at the start and the end.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path


def _data(root: Path) -> None:
    if (root / "splits" / "default" / "test.txt").is_file():
        return
    from cylsfm.data.splits import make_splits
    from cylsfm.data.synth import generate_dataset

    generate_dataset(
        root, sequences=16, frames=150, width=256, height=64, seed=0, splits=False, progress=False
    )
    make_splits(root, mode="sequence", fractions=(12 / 16, 1 / 16, 3 / 16), seed=0)


def _train(out: Path, steps: int, minutes: float) -> float:
    run = out / "run"
    cmd = [sys.executable, "-m", "cylsfm.cli", "train", "--data", str(out / "data"), "--out", str(run)]
    cmd += ["--size", "256x64", "--max-steps", str(steps), "--minutes", str(minutes), "--device", "cpu"]
    cmd += ["--no-progress", "log_every=1", "checkpoint_every=5000", "image_every=0"]
    if (run / "checkpoints" / "latest.pt").is_file():
        cmd.append("--resume")
    t0 = time.monotonic()
    subprocess.run(cmd, check=True)
    return time.monotonic() - t0


def report(out: Path, steps: int) -> dict:
    """Read ``OUT/run/metrics.jsonl`` and ``OUT/parts.json`` into the soak's summary."""
    rows = [json.loads(line) for line in (out / "run" / "metrics.jsonl").read_text().splitlines() if line]
    parts = json.loads((out / "parts.json").read_text()) if (out / "parts.json").is_file() else []
    values = [v for r in rows for k, v in r.items() if isinstance(v, float) and k not in ("time",)]
    bad = [
        (r["step"], k) for r in rows for k, v in r.items() if isinstance(v, float) and not math.isfinite(v)
    ]
    last = rows[-1]["step"] if rows else 0
    return {
        "steps": last,
        "target_steps": steps,
        "complete": last >= steps,
        "logged_rows": len(rows),
        "distinct_steps_logged": len({r["step"] for r in rows}),
        "values_checked": len(values),
        "non_finite": len(bad),
        "first_non_finite": bad[:5],
        "max_grad_norm": max((r.get("grad_norm", 0.0) for r in rows), default=None),
        "loss_first_100": sum(r["total"] for r in rows[:100]) / max(len(rows[:100]), 1),
        "loss_last_100": sum(r["total"] for r in rows[-100:]) / max(len(rows[-100:]), 1),
        "parts": parts,
        "seconds": sum(p["seconds"] for p in parts),
        "seconds_per_step": sum(p["seconds"] for p in parts) / max(last, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("soak"))
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--minutes", type=float, default=150.0, help="budget of this part")
    ap.add_argument("--report", action="store_true", help="only report what is there")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.report:
        _data(args.out / "data")
        before = (
            report(args.out, args.steps)["steps"] if (args.out / "run" / "metrics.jsonl").is_file() else 0
        )
        seconds = _train(args.out, args.steps, args.minutes)
        after = report(args.out, args.steps)["steps"]
        parts_file = args.out / "parts.json"
        parts = json.loads(parts_file.read_text()) if parts_file.is_file() else []
        parts.append({"from": before, "to": after, "seconds": round(seconds, 1), "date": time.strftime("%F")})
        parts_file.write_text(json.dumps(parts, indent=1))
    summary = report(args.out, args.steps)
    (args.out / "report.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
