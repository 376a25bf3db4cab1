"""Loop closure on rides that come back, and on rides that look alike but never do: the commands and
figures behind RESULTS.md's loop-closure table.

Usage::

    python experiments/loops.py CHECKPOINT OUT [--towns 1 8 15] [--routes block eight back stairs]

For each town (a sequence index of the benchmark, ``experiments/run.sh``'s seed 0: the same town as the
benchmark's ride of that index, ``town_frames=150``) and route, a ride is generated at 256x64
(``cylsfm synth``'s routes: ``block`` once around a block, ``eight`` a figure eight, ``back`` out and back
in the opposite direction; ``stairs`` in a town whose buildings all look alike, never a place twice;
``long``: a 1000-frame staircase in the plain town, for the time the loops add when nothing comes back;
``long-back``: a 1000-frame ride out and back in a town built for 1000 frames, for their time when
loops are verified and closed)
and ``cylsfm odometry --refine --loops`` runs on it (with ``--steady-height``, odometry's step lengths in
the unit of the fitted camera height, the column ``APE refined`` still the plain refinement's, ``APE
steady height`` the run's own odometry without the loops, the ratio to it in brackets; with
``--true-depth``, on the ride's true depth: what the loops give where the depth is not the limit). One run
gives both trajectories: refined without the loops (``refined``) and with them (``loops closed``); when no
loop is accepted they are the same.
Per ride: APE (Sim(3)) of both, the end-to-start gap of a closed ride as a fraction of its length (after
the Sim(3) alignment's scale), the loops accepted, the wrong ones among them (a relative pose more than 5
degrees or 2 m plus a tenth of the distance from the truth: :func:`judge`), the yaw of the accepted loops,
and the time the loops took. Printed and saved as
``OUT/table.json``. The default towns are the benchmark's held-out test towns; the loop settings were
chosen on training towns (``--towns 0 2 3``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import cylsfm
from cylsfm.data.io import read_tum
from cylsfm.data.synth import SynthConfig, generate_dataset
from cylsfm.errors import InputError
from cylsfm.evaluate.motion import rotation_error_deg
from cylsfm.evaluate.pose_metrics import trajectory_metrics
from cylsfm.odometry import OdometrySettings

SEED = 0  # experiments/run.sh's benchmark
FRAMES = {"block": 350, "eight": 520, "back": 400, "stairs": 400, "long": 1000, "long-back": 1000}
#: the synth route of each ride kind ("long": a 1000-frame staircase in the plain town, for the time)
ROUTE = {
    "block": "block",
    "eight": "eight",
    "back": "back",
    "stairs": "stairs",
    "long": "stairs",
    "long-back": "back",
}
#: the ride length each kind's town is built for (the benchmark's 150 frames: the same town as its ride)
TOWN_FRAMES = {"long-back": 1000}
CLOSED = ("block", "eight")


def make_ride(root: Path, town: int, route: str) -> Path:
    """The ride ``route`` in town ``town`` (256x64), generated once: the first frame count near
    ``FRAMES[route]`` for which the town has such a route."""
    seq = root / f"seq_{town:03d}"
    if (seq / "poses.txt").is_file():
        return seq
    for frames in FRAMES[route] + np.array([0, 50, -50, 100, -100, 150, 200]):
        try:
            cfg = SynthConfig(
                route=ROUTE[route], town_frames=TOWN_FRAMES.get(route, 150), alike=route == "stairs"
            )
            generate_dataset(
                root, sequences=1, first_index=town, frames=int(frames), width=256, height=64, seed=SEED,
                config=cfg, progress=False, overwrite=True,
            )  # fmt: skip
            return seq
        except InputError:
            continue
    raise SystemExit(f"town {town} has no {route} route of about {FRAMES[route]} frames")


def judge(pair: dict, gt: np.ndarray, out: Path) -> dict:
    """A loop of ``odometry.json`` against the truth ``gt`` ``[M,4,4]``: its rotation and translation errors
    (degrees; metres, the loop's translation brought to metres by the refined odometry's scale over the
    ten steps around its first frame, read from the run's state in ``out``), the true distance between
    its frames and whether it is right (within 5 degrees and 2 m plus a tenth of that distance)."""
    with np.load(out / ".odometry-state.npz", allow_pickle=False) as state:
        steps = state["refined"]  # T_{k->k+1}, the odometry's unit
    i, j = pair["i"], pair["j"]
    pose, truth = np.asarray(pair["pose"]).reshape(4, 4), np.linalg.inv(gt[j]) @ gt[i]
    lo, hi = max(0, i - 5), min(len(steps), i + 5)
    scale = np.linalg.norm(np.diff(gt[lo : hi + 1, :3, 3], axis=0), axis=1).sum() / max(
        np.linalg.norm(steps[lo:hi, :3, 3], axis=1).sum(), 1e-9
    )
    rotation = float(rotation_error_deg(pose, truth))
    translation = float(np.linalg.norm(scale * pose[:3, 3] - truth[:3, 3]))
    metres = float(np.linalg.norm(gt[i, :3, 3] - gt[j, :3, 3]))
    right = rotation < 5 and translation < 2 + 0.1 * metres
    return {
        "rotation_error_deg": rotation,
        "translation_error_m": translation,
        "metres": metres,
        "right": right,
    }


def measure(
    seq: Path, out: Path, checkpoint: str, true_depth: bool = False, steady_height: bool = False
) -> dict:
    depth_from = seq.parent if true_depth else None
    settings = OdometrySettings(
        progress=False,
        refine=True,
        loops=True,
        depth_from=depth_from,
        steady_height=steady_height,
        bundle=False,
    )
    result = cylsfm.odometry(seq, checkpoint, out, settings)
    times, gt = read_tum(seq / "poses.txt")
    length = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    metrics = result.metrics or {}
    # without loops (the run's own odometry: with --steady-height its lengths, else the plain refinement)
    unlooped = metrics.get("steady height", metrics["refined"])
    closed = metrics.get("loops closed", unlooped)
    stats, _ = trajectory_metrics(gt, times, result.c2w, times)
    gap = float(np.linalg.norm(result.c2w[-1, :3, 3] - result.c2w[0, :3, 3])) * stats["scale"] / length
    loops = result.loops or {"pairs": [], "verified": 0, "accepted": 0}
    accepted = [p for p in loops["pairs"] if p["accepted"]]
    wrong = [p for p in accepted if not judge(p, gt, out)["right"]]
    yaws = [abs(p["yaw_deg"]) for p in accepted]
    timings = result.timings
    loop_seconds = sum(timings.get(k, 0.0) for k in ("place descriptors", "loops", "pose graph"))
    return {
        "frames": len(result.c2w),
        "length_m": length,
        "ape_refined": metrics["refined"]["ape_rmse"],
        "ape_loops": closed["ape_rmse"],
        "ape_steady": unlooped["ape_rmse"] if "steady height" in metrics else None,
        "ratio": closed["ape_rmse"] / metrics["refined"]["ape_rmse"],
        "gap_fraction": gap,
        "true_gap_fraction": float(np.linalg.norm(gt[-1, :3, 3] - gt[0, :3, 3])) / length,
        "verified": loops["verified"],
        "accepted": loops["accepted"],
        "wrong": len(wrong),
        "yaw_deg_max": max(yaws) if yaws else None,
        "yaw_deg_min": min(yaws) if yaws else None,
        "constant_velocity": metrics["constant_velocity"]["ape_rmse"],
        "seconds": result.seconds,
        "loop_seconds": loop_seconds,
    }


def show(table: dict) -> None:
    print(
        "| ride | frames (m) | APE refined | APE steady height | APE loops closed | ratio (to the same "
        "run without loops) | end-start gap / length | loops accepted / verified | wrong | yaw of loops (deg) "
        "| const. vel. | loop time / total (s) |"
    )
    print("|" + "---|" * 12)
    for name, r in table.items():
        yaw = "-" if r["yaw_deg_min"] is None else f"{r['yaw_deg_min']:.0f}-{r['yaw_deg_max']:.0f}"
        gap = f"{r['gap_fraction']:.2%} (true {r['true_gap_fraction']:.1%})"
        steady = "-" if r.get("ape_steady") is None else f"{r['ape_steady']:.3f}"
        same = r["ape_loops"] / (r.get("ape_steady") or r["ape_refined"])  # to the same run without loops
        print(
            f"| {name} | {r['frames']} ({r['length_m']:.0f}) | {r['ape_refined']:.3f} | {steady} | "
            f"{r['ape_loops']:.3f} | {r['ratio']:.2f}x ({same:.2f}x) | {gap} | {r['accepted']} / "
            f"{r['verified']} | {r['wrong']} | {yaw} | "
            f"{r['constant_velocity']:.2f} | {r['loop_seconds']:.1f} / {r['seconds']:.1f} |"
        )


def ride_arguments(description: str, towns: list[int], routes: list[str]) -> argparse.Namespace:
    """The command line of a script that runs rides: ``CHECKPOINT OUT [--towns ...] [--routes ...]``."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("checkpoint")
    p.add_argument("out", type=Path)
    p.add_argument("--towns", type=int, nargs="*", default=towns)
    p.add_argument("--routes", nargs="*", default=routes)
    p.add_argument(
        "--true-depth", action="store_true", help="the refinement and the loops on the rides' true depth"
    )
    p.add_argument(
        "--steady-height",
        action="store_true",
        help="odometry's --steady-height: step lengths in the unit of the fitted camera height",
    )
    return p.parse_args()


def each_ride(args: argparse.Namespace):
    """``(name, sequence, odometry output)`` of every town and route asked for, each ride made once."""
    for town in args.towns:
        for route in args.routes:
            name = f"{route}-{town:03d}"
            yield name, make_ride(args.out / "data" / route, town, route), args.out / "odometry" / name


def main() -> None:
    args = ride_arguments(__doc__.split("\n\n")[0], [1, 8, 15], ["block", "eight", "back", "stairs"])
    table_file = args.out / "table.json"
    table = json.loads(table_file.read_text()) if table_file.is_file() else {}
    for name, seq, out in each_ride(args):
        table[name] = measure(seq, out, args.checkpoint, args.true_depth, args.steady_height)
        args.out.mkdir(parents=True, exist_ok=True)
        table_file.write_text(json.dumps(table, indent=2) + "\n")
        print(name, json.dumps(table[name]), flush=True)
    show(table)


if __name__ == "__main__":
    main()
