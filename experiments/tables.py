"""Print the Markdown tables of RESULTS.md from the JSON files that ``cylsfm evaluate`` wrote.

Usage: ``python experiments/tables.py RUN_DIR[:LABEL] ...`` where each RUN_DIR holds ``depth.json``,
``pose.json`` and (optionally) ``pose_yaw.json`` and ``pose_yaw_SEED.json`` (several rolls). The
baselines are printed once, from the first run.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from cylsfm.evaluate.depth_metrics import DEPTH_METRICS
from cylsfm.evaluate.pose import POSE_TABLE_METRICS
from cylsfm.evaluate.tables import markdown_row, markdown_rule


def _load(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _header(columns: list[str]) -> list[str]:
    return [markdown_row("", columns), markdown_rule(len(columns))]


def depth_table(runs: list[tuple[str, Path]]) -> list[str]:
    lines = _header(list(DEPTH_METRICS))
    base = None
    for label, run in runs:
        d = _load(run / "depth.json")
        if d is None:
            continue
        base = base or d["baselines"]
        lines.append(markdown_row(label, [d[k] for k in DEPTH_METRICS]))
    if base:
        for name, b in base.items():
            lines.append(markdown_row(name.replace("_", "-") + " baseline", [b[k] for k in DEPTH_METRICS]))
        lines.append("")
        for label, run in runs:
            d = _load(run / "depth.json")
            if d is not None:
                c, p = base["constant"]["abs_rel"], base["per_row"]["abs_rel"]
                lines.append(
                    f"{label}: abs_rel {d['abs_rel'] / c:.3f}x constant, {d['abs_rel'] / p:.3f}x per-row"
                )
    return lines


def seam_table(runs: list[tuple[str, Path]]) -> list[str]:
    """Depth next to the seam of the panoramas and around the image centre (``depth.json``'s ``seam``
    and ``centre`` entries)."""
    lines = _header(list(DEPTH_METRICS))
    for part in ("seam", "centre"):
        base = None
        for label, run in runs:
            d = _load(run / "depth.json")
            if d is None or not d.get(part):
                continue
            base = base or d["baselines"]
            lines.append(markdown_row(f"{label} @{part}", [d[part][k] for k in DEPTH_METRICS]))
        for name, b in (base or {}).items():
            if b and b.get(part):
                label = name.replace("_", "-") + f" baseline @{part}"
                lines.append(markdown_row(label, [b[part][k] for k in DEPTH_METRICS]))
    return lines


def pose_table(runs: list[tuple[str, Path]], name: str) -> list[str]:
    keys = POSE_TABLE_METRICS
    lines = _header(list(keys))
    base = None
    for label, run in runs:
        d = _load(run / name)
        if d is None:
            continue
        base = base or d["baselines"]
        lines.append(markdown_row(label, [d[k] for k in keys]))
    if base:
        for bname, b in base.items():
            if b is not None:
                lines.append(markdown_row(bname.replace("_", " "), [b.get(k) for k in keys]))
    return lines


def motion_table(runs: list[tuple[str, Path]], name: str = "pose.json") -> list[str]:
    """Does the pose estimate measure the motion? (``pose.json``'s ``motion`` diagnostics, with the compass
    and constant velocity from the first run, the bounds, and each run's verdict.)"""
    from cylsfm.evaluate.motion import MOTION_COLUMNS, verdict_line

    lines = _header([h for _, h in MOTION_COLUMNS])
    refs, verdicts = None, []
    for label, run in runs:
        d = _load(run / name)
        if d is None or not d.get("motion"):
            continue
        m = d["motion"]
        refs = refs or m
        lines.append(markdown_row(label, [m["model"].get(k) for k, _ in MOTION_COLUMNS]))
        verdicts.append(f"{label}: {verdict_line(m)}")
    if refs:
        for ref in ("compass", "constant_velocity"):
            if refs.get(ref):
                lines.append(
                    markdown_row(ref.replace("_", " "), [refs[ref].get(k) for k, _ in MOTION_COLUMNS])
                )
        lines += [
            "",
            f"{refs['n_steps']} steps, {refs['n_turning']} turning (|yaw| > {refs['turn_deg']:g} deg)",
        ]
    return [*lines, "", *verdicts]


def yaw_seeds(runs: list[tuple[str, Path]]) -> list[str]:
    """Snippet ATE over several random-yaw rolls of the test rides (``pose_yaw_SEED.json`` files)."""
    lines = _header(["rolls", "snippet ATE mean (over rolls)", "min", "max", "constant velocity", "unrolled"])
    for label, run in runs:
        files = sorted(run.glob("pose_yaw_*.json"))
        if not files:
            continue
        ds = [_load(f) for f in files]
        ate = [d["ate_mean"] for d in ds]
        cv = sum(d["baselines"]["constant_velocity"]["ate_mean"] for d in ds) / len(ds)
        plain = _load(run / "pose.json")
        mean = sum(ate) / len(ate)
        cells = [
            f"{len(ds)} seeds x 3 rides",
            mean,
            min(ate),
            max(ate),
            cv,
            plain["ate_mean"] if plain else None,
        ]
        lines.append(markdown_row(label, cells))
    return lines


def per_sequence(runs: list[tuple[str, Path]]) -> list[str]:
    lines = []
    for label, run in runs:
        d = _load(run / "pose.json")
        if d is None:
            continue
        parts = []
        for seq, s in sorted(d.get("sequences", {}).items()):
            parts.append(f"{seq} {s['model']['ape_rmse']:.2f} (cv {s['constant_velocity']['ape_rmse']:.2f})")
        lines.append(f"{label} APE rmse per sequence: " + ", ".join(parts))
    return lines


def main(argv: list[str]) -> None:
    runs = []
    for arg in argv:
        path, _, label = arg.partition(":")
        runs.append((label or Path(path).name, Path(path)))
    for title, lines in (
        ("depth", depth_table(runs)),
        ("depth next to the seam and around the centre", seam_table(runs)),
        ("pose", pose_table(runs, "pose.json")),
        ("is the motion measured?", motion_table(runs)),
        ("pose, test rides rolled by random yaws", pose_table(runs, "pose_yaw.json")),
        ("pose, several random yaw rolls", yaw_seeds(runs)),
        ("per sequence", per_sequence(runs)),
    ):
        print(f"## {title}\n")
        print("\n".join(lines) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
