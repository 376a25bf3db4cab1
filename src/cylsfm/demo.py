"""``cylsfm demo``: the whole method on built-in synthetic data, within a time budget.

1. Generate a small synthetic 360-degree street dataset with ground truth (``cylsfm synth``): training
   towns and held-out test towns (a split by sequence).
2. Train DispNet and PoseExpNet without labels (the default, improved recipe) at a reduced size for the
   time that remains of the budget.
3. Evaluate depth and ego-motion on the held-out towns next to the baselines that "learned nothing"
   (median-scaled constant depth, the per-row depth prior, zero motion, constant velocity).
4. Write ``report.md`` with the tables, the loss curve and pictures (input, predicted depth, ground truth),
   and print the tables.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_write_bytes
from .data.format import load_depth, load_image, save_png
from .data.synth import generate_dataset
from .errors import InputError

__all__ = ["run_demo"]


def run_demo(
    out: str | Path,
    minutes: float = 20.0,
    seed: int = 0,
    width: int = 256,
    height: int = 64,
    sequences: int = 16,
    test_sequences: int = 3,
    frames: int = 150,
    eval_reserve_minutes: float = 2.0,
    progress: bool = True,
) -> dict[str, Any]:
    """Run the demonstration into ``out``; returns the evaluation results.

    Args:
        out: output directory (``data/``, ``run/``, ``figures/``, ``report.md``, ``depth.json``,
            ``pose.json``).
        minutes: the whole budget; training gets what generating the data and ``eval_reserve_minutes``
            leave of it (at least 6 seconds).
        seed: seed of the synthetic data, its split and training.
        width, height: size of the generated panoramas and of training (pixels).
        sequences: synthetic rides (towns) to generate; ``test_sequences`` of them are held out for the
            evaluation, one for validation, the rest (at least one) trained on.
        frames: frames per ride.
        eval_reserve_minutes: time kept for evaluating and writing the report.
        progress: show progress bars.

    Raises:
        InputError: fewer than ``test_sequences + 2`` sequences.
    """
    if sequences < test_sequences + 2:
        raise InputError(
            f"--sequences must leave at least 2 rides for training and validation, got {sequences}"
        )
    t0 = time.monotonic()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = out / "data"
    print(
        f"[1/4] generating {sequences} synthetic rides of {frames} frames at {width}x{height} ...", flush=True
    )
    _generate(data, sequences, test_sequences, frames, width, height, seed, progress)
    gen_minutes = (time.monotonic() - t0) / 60
    train_minutes = max(minutes - gen_minutes - eval_reserve_minutes, 0.1)
    print(f"      done in {gen_minutes:.1f} min", flush=True)

    print(
        f"[2/4] training for {train_minutes:.1f} min (the default recipe, {width}x{height}, batch 4) ...",
        flush=True,
    )
    cfg, summary = _train(data, out / "run", width, height, train_minutes, seed, progress)
    print(f"      {summary['steps']} steps in {summary['seconds'] / 60:.1f} min", flush=True)

    print("[3/4] evaluating on the held-out towns ...", flush=True)
    predictor, depth, pose = _evaluate(out, data)

    print("[4/4] writing the report ...", flush=True)
    from .evaluate.depth import depth_json, format_depth_table
    from .evaluate.pose import format_pose_table, pose_json

    depth_table, pose_table = format_depth_table(depth), format_pose_table(pose)
    _write_report(
        out, cfg, summary, depth, pose, depth_table, pose_table, predictor, data, time.monotonic() - t0
    )
    print()
    print(depth_table)
    print()
    print(pose_table)
    print(f"\nreport: {out / 'report.md'}  (total {(time.monotonic() - t0) / 60:.1f} min)")
    return {"depth": depth_json(depth), "pose": pose_json(pose), "train": summary}


def _generate(
    data: Path,
    sequences: int,
    test_sequences: int,
    frames: int,
    width: int,
    height: int,
    seed: int,
    progress: bool,
) -> None:
    """The synthetic rides in ``data``, split by sequence: ``test_sequences`` test towns, one validation
    town, the others for training. Skipped when ``data`` already holds its test split."""
    if (data / "splits" / "default" / "test.txt").exists():
        return
    test_fraction = test_sequences / sequences
    fractions = (1 - test_fraction - 1 / sequences, 1 / sequences, test_fraction)
    generate_dataset(data, sequences=sequences, frames=frames, width=width, height=height, seed=seed,
                     progress=progress, overwrite=True, splits=True, split_fractions=fractions)  # fmt: skip


def _train(data: Path, run: Path, width: int, height: int, minutes: float, seed: int, progress: bool):
    """Train the default recipe on ``data`` into ``run`` for ``minutes`` (resuming a run that is there);
    returns the configuration and the trainer's summary."""
    from .model.config import apply_overrides, preset
    from .train.trainer import train

    cfg = apply_overrides(
        preset("default"),
        [f"data.root='{data}'", f"data.width={width}", f"data.height={height}", f"minutes={minutes}",
         f"seed={seed}", "max_steps=1000000", "checkpoint_every=0"],
    )  # fmt: skip
    resume = (run / "checkpoints" / "latest.pt").exists()  # a demo stopped before: continued
    summary = train(cfg, run, resume=resume, progress=progress, overwrite=not resume)
    return cfg, summary


def _evaluate(out: Path, data: Path):
    """Depth and ego-motion of the trained run on the test towns (``depth.json``, ``pose.json``,
    ``trajectories/``); returns the predictor and both results."""
    from .evaluate.depth import depth_json, evaluate_depth
    from .evaluate.pose import evaluate_pose, pose_json
    from .model import Predictor

    predictor = Predictor.from_checkpoint(out / "run", device="auto")
    depth = evaluate_depth(predictor, data, split="test", prior_split="train")
    pose = evaluate_pose(predictor, data, split="test", out=out / "trajectories")
    atomic_write_bytes(out / "depth.json", json.dumps(depth_json(depth), indent=2).encode())
    atomic_write_bytes(out / "pose.json", json.dumps(pose_json(pose), indent=2).encode())
    return predictor, depth, pose


def _write_report(out, cfg, summary, depth, pose, depth_table, pose_table, predictor, data, seconds) -> None:
    from .data.format import scan_dataset
    from .data.splits import read_split

    figures = out / "figures"
    figures.mkdir(exist_ok=True)
    _loss_curve(out / "run" / "metrics.jsonl", figures / "loss.png")
    # pictures: input, predicted depth, ground truth for a few held-out frames
    test = read_split(data / "splits" / "default" / "test.txt", data)
    seqs = {s.name: s for s in scan_dataset(data)}
    picks = [test[i] for i in np.linspace(0, len(test) - 1, 4).astype(int)] if test else []
    rows = []
    for seq_name, stem in picks:
        seq = seqs[seq_name]
        idx = [p.stem for p in seq.images].index(stem)
        rows.append(_picture(predictor, seq, idx, figures / f"{seq_name}_{stem}.png"))
    b = depth.get("baselines", {})
    model_abs = _get(depth, "abs_rel")
    const_abs = _get(b.get("constant") or {}, "abs_rel")
    row_abs = _get(b.get("per_row") or {}, "abs_rel")
    lines = [
        "# cylsfm demo report",
        "",
        f"Synthetic 360-degree street rides (`cylsfm synth`), {cfg.data.width}x{cfg.data.height} cylindrical "
        f"panoramas, split by sequence: the test towns were never seen in training. Training: preset "
        f"`{cfg.preset}`, {summary['steps']} steps in {summary['seconds'] / 60:.1f} min on "
        f"{predictor.device}. Whole demo: {seconds / 60:.1f} min.",
        "",
        "## Depth (held-out towns, per-image median scaling, depth capped to [1e-3, 80] m)",
        "",
        "```",
        depth_table,
        "```",
        "",
    ]
    if model_abs is not None and const_abs and row_abs:
        lines += [
            f"abs_rel of the model is {model_abs / const_abs:.2f}x that of the median-scaled constant depth and "
            f"{model_abs / row_abs:.2f}x that of the per-row prior (each row predicts its median training depth).",
            "",
        ]
    lines += ["## Ego-motion (held-out towns)", "", "```", pose_table, "```", ""]
    lines += ["## Training loss", "", "![loss](figures/loss.png)", ""]
    if rows:
        lines += [
            "## Pictures: input, predicted depth, ground truth",
            "",
            "Held-out frames enlarged to at least 1024 pixels wide. Depth is coloured by inverse depth, near "
            "bright and far dark, on one scale for the prediction and the ground truth: the colour bar under "
            "each picture is labelled in metres.",
            "",
        ]
        lines += [f"![{p.stem}](figures/{p.name})" for p in rows] + [""]
    plots = sorted((out / "trajectories").glob("*.png")) if (out / "trajectories").exists() else []
    if plots:
        lines += ["## Trajectories (top view, Sim(3)-aligned)", ""]
        lines += [f"![{p.stem}]({p.relative_to(out)})" for p in plots] + [""]
    lines += [
        "## Reproduce",
        "",
        "```sh",
        f"cylsfm demo --out {out} --minutes {cfg.minutes:.0f}",
        "```",
        "",
        "The run directory `run/` holds the configuration, the checkpoints and the TensorBoard logs "
        "(`tensorboard --logdir run/tb`).",
    ]
    atomic_write_bytes(out / "report.md", ("\n".join(lines) + "\n").encode())


def _get(d: dict, key: str) -> float | None:
    v = d.get(key)
    if v is None and isinstance(d.get("model"), dict):
        v = d["model"].get(key)
    return float(v) if v is not None else None


def _picture(predictor, seq, idx: int, path: Path) -> Path:
    import torch

    from .export.colorize import depth_panels

    image = load_image(seq.images[idx])
    x = torch.from_numpy(np.array(image)).permute(2, 0, 1)[None].float() / 255
    pred = predictor.depth(x, seq.camera)[0, 0].cpu().numpy()
    gt = load_depth(seq.depths[idx]) if seq.depths and seq.depths[idx] else np.zeros_like(pred)
    valid = gt > 0
    if valid.any():  # show the prediction at the ground truth's scale, as the metrics see it
        pred = pred * np.median(gt[valid]) / np.median(pred[valid])
    # one colour scale for both, from the ground truth's 2nd to 95th percentile of depth (metres); without
    # ground truth, the prediction's own range in its units
    limits = (
        (float(np.percentile(gt[valid], 2)), float(np.percentile(gt[valid], 95))) if valid.any() else None
    )
    unit = "metres" if valid.any() else "network units"
    labels = [
        f"input: held-out frame {seq.name}/{seq.images[idx].stem}",
        "predicted depth" + (" (scaled to the ground truth's median)" if valid.any() else ""),
        "ground truth (black: no depth, the sky)",
    ]
    # enlarged to at least 1024 px wide (the depth by repeating pixels), with the colour scale below
    save_png(path, depth_panels(image, [pred, gt], unit, labels=labels, limits=limits))
    return path


def _loss_curve(metrics: Path, path: Path) -> None:
    if not metrics.exists():
        return
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    if not rows:
        return
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.2), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    steps = np.array([r["step"] for r in rows])
    for key in ("total", "photometric"):
        vals = np.array([r.get(key, np.nan) for r in rows])
        ax.plot(steps, vals, label=key, lw=1)
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
