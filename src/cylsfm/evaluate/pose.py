"""Ego-motion evaluation: SfMLearner's snippet ATE and full-trajectory APE / RPE (with ``evo``), and baselines.

**Frames.** With a model trained with frame stride ``s`` the evaluation uses every ``s``-th frame of a
sequence (frames ``0, s, 2s, ...``, the *chain*); consecutive chain frames are one network step apart.
Evaluated sequences are those with at least one target in the split file (all of their frames, not just
the listed targets), or every sequence when ``split`` is ``None``.

**Trajectories from the pose network.** The network sees ``L = seq_length`` frames (usually 3) with the
centre one as target and predicts ``T_tgt_to_src`` for each source. It is run once on the window centred
on every chain frame ``c`` that has a full window (``k <= c <= M-1-k``, ``k = (L-1)//2``). The motion
between consecutive frames is taken from the window centred on the earlier frame, ``c = j``:
``T_{j->j+1}`` is its prediction for the source ``j+1``. Near the ends, where that window does not exist,
the nearest full window ``c = clamp(j, k, M-1-k)`` (which holds both frames) is used:
``T_{j->j+1} = T_{c->j+1} @ inv(T_{c->j})`` (with ``T_{c->c} = I``); e.g. for ``L = 3`` the first step is
``inv(T_{1->0})``. The steps are chained into camera-to-world poses, ``c2w_0 = I``,
``c2w_{j+1} = c2w_j @ inv(T_{j->j+1})`` (:func:`chain_poses`), in the network's (unknown) units.

**Snippet ATE** (SfMLearner, Zhou et al. 2017): for every run of ``snippet`` (default 5) consecutive chain
frames (overlapping: one snippet starts at every frame), both trajectories are expressed relative to the
snippet's first frame (positions of ``inv(c2w_0) @ c2w_i``), one scale ``s = sum(gt . pred) / sum(pred .
pred)`` is fitted, and ``ATE = sqrt(sum_i ||gt_i - s pred_i||^2) / N``. Note the division of the *root* of
the summed squared error by ``N`` (not a root mean square): that is what SfMLearner's published
evaluation code computes, and it reproduces the paper's numbers. Mean and standard deviation over all
snippets of all evaluated sequences: ``ate_mean``, ``ate_std`` (metres). Predicted snippets are cut from
the chained trajectory, which is the same as chaining the snippet's own consecutive steps.

**Full trajectories** (``evo``): the chained trajectory is compared with ``poses.txt`` by ``evo``'s APE
(translation part) after a Sim(3) Umeyama alignment (``align(correct_scale=True)`` on a copy) and RPE
between consecutive chain frames (translation, on the aligned copy, so in metres; and rotation angle in
degrees). Per-sequence numbers are averaged over sequences (each sequence weighs the same).

**Baselines**, on the same snippets and frames:

- *zero motion*: the camera never moves. Snippet ATE with a zero prediction (the fitted scale is 0). A
  single point cannot be Sim(3)-aligned (Umeyama needs non-collinear points), so its full-trajectory APE is
  that of a camera standing at the ground truth's centroid (the best any alignment of one point can do);
  no RPE.
- *constant velocity*: the same step every frame along the camera's +z axis, no rotation; scale fitted per
  snippet like a prediction. For full trajectories its best Sim(3) alignment is computed in closed form:
  ``s R (0, 0, i) + t = i v + t`` for any vector ``v``, so the aligned positions are the least-squares line
  ``c + v i`` through the ground-truth positions (``evo``'s Umeyama refuses collinear points); ``evo``
  then computes APE and RPE on that aligned trajectory.

**Other methods** (``trajectory=``): TUM files (camera-to-world) of any method are scored the same way.
Their poses are matched to the ground truth of the chain frames by timestamp (nearest, within half the
smallest gap between ground-truth timestamps): write timestamps equal to those of the dataset's
``poses.txt`` (the trajectories this module writes do). Snippets are cut from the matched poses (a snippet
with an unmatched frame is skipped); full-trajectory metrics use the matched poses.

The measures are small functions in :mod:`cylsfm.evaluate.pose_metrics` (re-exported here); this module
runs the network, reads other methods' files and puts the results together.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data import DatasetError, DatasetWarning, SequenceInfo, load_mask, scan_dataset, write_tum
from ..errors import InputError
from ..geometry import roll_pose
from .frames import (
    PathLike,
    check_batch_size,
    check_rollable,
    check_yaw_roll,
    draw_roll,
    model_source,
    split_entries,
)
from .motion import MotionRecord, format_motion_table, steps_of
from .plots import plot_trajectories
from .pose_metrics import (
    TRAJECTORY_METRICS,
    ate_positions,
    ate_summary,
    average_metrics,
    baseline_trajectories,
    chain_poses,
    consecutive_from_windows,
    constant_velocity_trajectory,
    relative_positions,
    snippet_ate,
    snippet_ates,
    trajectory_metrics,
)
from .pose_source import compass_steps, predict_consecutive, predict_windows, read_matched, trajectory_file
from .tables import ratio, text_row

__all__ = [
    "POSE_TABLE_METRICS",
    "TRAJECTORY_METRICS",
    "ate_positions",
    "chain_poses",
    "consecutive_from_windows",
    "constant_velocity_trajectory",
    "evaluate_pose",
    "format_pose_table",
    "plot_trajectories",
    "pose_json",
    "predict_consecutive",
    "relative_positions",
    "snippet_ate",
    "snippet_ates",
    "trajectory_metrics",
]

#: The columns of the pose table (metres, degrees).
POSE_TABLE_METRICS = ("ate_mean", "ate_std", "ape_rmse", "rpe_trans_rmse", "rpe_rot_deg_rmse")

#: The zero-motion baseline has no rotation to speak of: APE only.
_ZERO_MOTION_METRICS = ("ape_rmse", "ape_mean", "ape_median", "ape_max")


# --------------------------------------------------------------------------------------- one run
def _mask(seq: SequenceInfo) -> np.ndarray | None:
    """The sequence's ``mask.png`` ``[H,W]`` (an occluder fixed to the camera: 0), or ``None``."""
    return None if seq.mask is None else load_mask(seq.mask)


@dataclass
class _Run:
    """One pose evaluation: where the estimates come from (a predictor, or TUM ``files`` by sequence
    name), the options, and the snippet ATEs of the sequences scored so far."""

    predictor: Any | None
    files: dict[str, Path]
    source: str
    step: int
    snippet: int
    batch_size: int
    progress: bool | None
    yaw_roll: int | None
    out_dir: Path | None
    snippets: dict[str, list[np.ndarray]] = field(
        default_factory=lambda: {"model": [], "zero_motion": [], "constant_velocity": [], "compass": []}
    )
    motion: MotionRecord = field(default_factory=MotionRecord)


def _check_options(
    given: Any, snippet: int, stride: int | None, batch_size: int, yaw_roll: int | None
) -> None:
    """Raise :class:`InputError` for an invalid option of :func:`evaluate_pose`."""
    if snippet < 2:
        raise InputError(f"snippet must be at least 2 frames, got {snippet}")
    if stride is not None and stride < 1:
        raise InputError(f"stride must be >= 1, got {stride}")
    check_batch_size(batch_size)
    check_yaw_roll(yaw_roll, given, "a given trajectory")


def _chosen_sequences(root: Path, split: Any, split_name: str) -> list[SequenceInfo]:
    """The sequences with a target in ``split`` (every sequence for ``None``)."""
    sequences = scan_dataset(root)
    entries = split_entries(root, split, split_name, sequences)
    names = None if entries is None else {s for s, _ in entries}
    chosen = [s for s in sequences if names is None or s.name in names]
    if not chosen:
        raise DatasetError(f"{root}: split {split} names no sequence")
    return chosen


def _open_run(given: Any, chosen: list[SequenceInfo], stride: int | None, **options: Any) -> _Run:
    """The run of :func:`evaluate_pose` for a predictor or a trajectory path ``given``."""
    if isinstance(given, (str, os.PathLike)):
        path = Path(given)
        files = {s.name: trajectory_file(path, s, len(chosen)) for s in chosen}
        return _Run(None, files, f"trajectory {path}", int(stride or 1), **options)
    if options["yaw_roll"] is not None:
        check_rollable(chosen)
    source = model_source(given)
    if getattr(given, "pose_iterations", 0):
        source += f", {given.pose_iterations} pose iterations"
    return _Run(given, {}, source, int(stride or given.frame_stride), **options)


def _estimate(
    run: _Run, seq: SequenceInfo, index: np.ndarray, times: np.ndarray, roll: int, info: dict
) -> Any:
    """``(c2w [M,4,4], matched bool [M], windows)`` of the chain frames ``index [M]`` of ``seq``: the
    model's chained trajectory (written to ``out`` when given) with its :class:`WindowPoses`, or the matched
    poses of a TUM file (windows ``None``); ``None`` when the chain is shorter than the model's window (with
    a warning)."""
    if run.predictor is None:
        return (*read_matched(run.files[seq.name], times), None)
    seq_length = int(run.predictor.window_length)
    if len(index) < seq_length:
        warnings.warn(
            f"{seq.path}: {len(index)} frames (stride {run.step}) are fewer than one window of {seq_length}; "
            "skipped",
            DatasetWarning,
            stacklevel=4,
        )
        return None
    images = [seq.images[i] for i in index]
    windows = predict_windows(
        run.predictor, images, seq.camera, run.batch_size, run.progress, seq.name, roll, mask=_mask(seq)
    )
    est = chain_poses(windows.steps(len(images)))
    if run.out_dir is not None:
        write_tum(run.out_dir / f"{seq.name}.txt", times, est)
        info["tum"] = str(run.out_dir / f"{seq.name}.txt")
    return est, np.ones(len(index), dtype=bool), windows


@dataclass
class _Estimate:
    """One sequence's estimate: camera-to-world poses ``c2w [M,4,4]``, which frames have one (``matched``),
    the network's windows (or ``None``) and the compass's chained trajectory (or ``None``)."""

    c2w: np.ndarray
    matched: np.ndarray
    windows: Any
    compass: np.ndarray | None = None


def _record_motion(run: _Run, gt: np.ndarray, est: _Estimate) -> None:
    """The consecutive steps of one sequence (both frames matched) into ``run.motion``."""
    both = est.matched[:-1] & est.matched[1:]
    compass = None if est.compass is None else steps_of(est.compass)[both]
    run.motion.add(steps_of(gt)[both], steps_of(est.c2w)[both], compass, est.windows)


def _score(
    run: _Run, seq: SequenceInfo, gt: np.ndarray, times: np.ndarray, est: _Estimate, info: dict
) -> None:
    """Score one sequence's estimate against its ground truth ``[M,4,4]``: snippet ATEs (kept in ``run``),
    the motion diagnostics' steps and, with at least 3 matched frames, the full-trajectory metrics of the
    model, the compass and the baselines (and the plot, with ``out``), all into ``info``."""
    ates = snippet_ates(gt, est.c2w, run.snippet, est.matched)
    for k, v in ates.items():
        run.snippets[k].append(v)
    if est.compass is not None:
        run.snippets["compass"].append(snippet_ates(gt, est.compass, run.snippet, est.matched)["model"])
    _record_motion(run, gt, est)
    info["n_snippets"] = len(ates["model"])
    info["ate_mean"] = float(ates["model"].mean()) if len(ates["model"]) else None
    sel = np.nonzero(est.matched)[0]
    if len(sel) < 3:
        return
    info["model"], aligned = trajectory_metrics(gt[sel], times[sel], est.c2w[sel], times[sel], max_diff=1e-6)
    base, curves = baseline_trajectories(gt[sel], times[sel], sel)
    info.update(base)
    curves = {"model (Sim(3)-aligned)": aligned, **curves}
    if est.compass is not None:
        info["compass"], along = trajectory_metrics(gt[sel], times[sel], est.compass[sel], times[sel], 1e-6)
        if along is not None:
            curves["compass (Sim(3)-aligned)"] = along
    if run.out_dir is not None:
        png = run.out_dir / f"{seq.name}.png"
        plot_trajectories(png, gt[sel, :3, 3], curves, title=f"{seq.name}: top view")
        info["plot"] = str(png)


def _sequence(run: _Run, seq: SequenceInfo, n_seq: int) -> dict[str, Any] | None:
    """Evaluate the ``n_seq``-th chosen sequence: its entry of ``"sequences"``, or ``None`` when skipped."""
    index = np.arange(0, len(seq), run.step)
    times = seq.timestamps[index] if seq.timestamps is not None else index.astype(np.float64)
    info: dict[str, Any] = {"n_frames": len(index)}
    gt = None if seq.poses is None else seq.poses[index]
    roll = 0
    if run.yaw_roll is not None:  # one roll per sequence; the ground truth turns with the images
        roll = draw_roll(seq.camera.width, run.yaw_roll, n_seq)
        info["yaw_roll_columns"] = roll
        if gt is not None:
            gt = roll_pose(gt, roll, seq.camera.width, camera_to_world=True)
    estimate = _estimate(run, seq, index, times, roll, info)
    if estimate is None:
        return None
    est = _Estimate(*estimate)
    info["n_matched"] = int(est.matched.sum())
    if gt is None:
        warnings.warn(
            f"{seq.path / 'poses.txt'}: not found; sequence {seq.name} not scored",
            DatasetWarning,
            stacklevel=3,
        )
        return info
    if seq.camera.wraps:  # the visual compass reads full panoramas only
        frames = [seq.images[i] for i in index]
        est.compass = chain_poses(compass_steps(frames, roll, width=seq.camera.width, mask=_mask(seq)))
    _score(run, seq, gt, times, est, info)
    return info


def _summary(run: _Run, per_seq: dict[str, dict[str, Any]], root: Path) -> dict[str, Any]:
    """``{"model", "zero_motion", "constant_velocity", "compass", "motion"}``: snippet ATEs over all
    snippets, full-trajectory metrics averaged over the scored sequences (``"compass"`` ``None`` unless
    every scored sequence is a full panorama), and the motion diagnostics."""
    if not any(len(v) for v in run.snippets["zero_motion"]) and not any(
        "model" in d for d in per_seq.values()
    ):
        raise DatasetError(
            f"{root}: nothing to score (evaluated sequences need poses.txt and at least {run.snippet} frames)"
        )
    scored = [d for d in per_seq.values() if "model" in d]
    out: dict[str, Any] = {}
    names = [("model", TRAJECTORY_METRICS), ("zero_motion", _ZERO_MOTION_METRICS)]
    names.append(("constant_velocity", TRAJECTORY_METRICS))
    if len(run.snippets["compass"]) == len(run.snippets["model"]):
        names.append(("compass", TRAJECTORY_METRICS))
    for name, keys in names:
        out[name] = {**ate_summary(run.snippets[name]), **average_metrics([d[name] for d in scored], keys)}
    out.setdefault("compass", None)
    out["motion"] = run.motion.summary()
    return out


# --------------------------------------------------------------------------------------- evaluation
def evaluate_pose(
    predictor_or_trajectory: Any,
    data_root: PathLike,
    split: str | PathLike | None = "test",
    split_name: str = "default",
    snippet: int = 5,
    stride: int | None = None,
    out: PathLike | None = None,
    batch_size: int = 8,
    progress: bool | None = False,
    yaw_roll: int | None = None,
) -> dict[str, Any]:
    """Evaluate ego-motion on a dataset's ground-truth poses, with the zero-motion and constant-velocity
    baselines (protocol in the module docstring).

    Args:
        predictor_or_trajectory: a :class:`cylsfm.model.Predictor`, or the TUM trajectory of another
            method: a directory with ``SEQ.txt`` per evaluated sequence, or one file when a single
            sequence is evaluated.
        data_root: the dataset root; evaluated sequences need ``poses.txt`` for the metrics (others are
            skipped with a warning, their trajectories still written).
        split: sequences with a target in this split (``"test"``, ``"val"``, ``"train"`` or a split file)
            are evaluated whole; ``None``: every sequence.
        split_name: the split directory under ``ROOT/splits``.
        snippet: frames per ATE snippet, at least 2.
        stride: frame step of the chain, at least 1 (default: the model's ``data.stride``; 1 for
            trajectories).
        out: directory for ``SEQ.txt`` (the model's chained trajectory, TUM, camera-to-world, network
            units, timestamps of ``poses.txt`` or the frame index) and ``SEQ.png`` (top view of the
            aligned trajectories); ``None``: write nothing.
        batch_size: windows per network call, at least 1.
        progress: show progress bars (``None``: when stderr is a terminal).
        yaw_roll: a seed: roll every frame of each evaluated sequence by a random number of columns
            (drawn per sequence) before the network sees it, as if the 360-degree camera had been mounted
            turned about its vertical axis. The ground truth is turned with it
            (:func:`cylsfm.geometry.roll_pose`: ``c2w' = c2w @ inv(yaw_matrix(2 pi k / W))``). Full
            panoramas and models only. This is how the paper's pose head (invariant to such rolls) and
            the yaw-equivariant head are compared.

    Returns:
        ``{"model": {ate_mean, ate_std, n_snippets, ape_rmse, ...}, "zero_motion": {...},
        "constant_velocity": {...}, "sequences": {SEQ: {...}}, "n_snippets", "snippet", "stride",
        "source", "data", "split", "split_name", "out", "yaw_roll"}``; see :func:`pose_json`.

    Raises:
        InputError: an invalid argument (see above).
        DatasetError: a missing or invalid dataset or trajectory file (named), or nothing to score.
    """
    _check_options(predictor_or_trajectory, snippet, stride, batch_size, yaw_roll)
    root = Path(data_root)
    chosen = _chosen_sequences(root, split, split_name)
    out_dir = None if out is None else Path(out)
    options = {"snippet": snippet, "batch_size": batch_size, "progress": progress, "yaw_roll": yaw_roll}
    run = _open_run(predictor_or_trajectory, chosen, stride, **options, out_dir=out_dir)
    per_seq: dict[str, dict[str, Any]] = {}
    for n_seq, seq in enumerate(chosen):
        info = _sequence(run, seq, n_seq)
        if info is not None:
            per_seq[seq.name] = info
    summary = _summary(run, per_seq, root)
    return {
        **summary,
        "sequences": per_seq,
        "n_snippets": summary["model"]["n_snippets"],
        "snippet": int(snippet),
        "stride": run.step,
        "source": run.source,
        "data": str(root),
        "split": None if split is None else str(split),
        "split_name": split_name,
        "out": None if out_dir is None else str(out_dir),
        "yaw_roll": yaw_roll,
    }


# --------------------------------------------------------------------------------------- reporting
def pose_json(result: dict[str, Any]) -> dict[str, Any]:
    """The JSON layout of a result of :func:`evaluate_pose`::

    {"ate_mean", "ate_std", "n_snippets",                         snippet ATE of the model (metres)
     "ape_rmse", "ape_mean", "ape_median", "ape_max",              Sim(3)-aligned APE, mean over sequences
     "rpe_trans_rmse", "rpe_rot_deg_rmse",                         RPE, delta 1 frame
     "baselines": {"zero_motion": {"ate_mean", "ate_std", "n_snippets", "ape_rmse", "ape_mean",
                                   "ape_median", "ape_max"},
                   "constant_velocity": {same keys as the model},
                   "compass": {same keys as the model} or None (not full panoramas)},
     "motion": {"turn_deg", "n_steps", "n_turning", "verdict": {"measured", "failures"},
                "model": {"yaw_slope", "yaw_correlation", "rot_err_deg", "rot_err_deg_turning",
                          "standing_ratio", "swap_cosine", "fb_trans_ratio", "fb_rot_deg", ...},
                "compass": {...} or None, "constant_velocity": {...}}     see cylsfm.evaluate.motion
     "sequences": {SEQ: {"n_frames", "n_matched", "n_snippets", "ate_mean", "model": {...},
                         "zero_motion": {...}, "constant_velocity": {...}, "tum", "plot"}},
     "meta": {"source", "data", "split", "split_name", "snippet", "stride", "out", "yaw_roll"}}
    """
    out = dict(result["model"])
    out["baselines"] = {
        "zero_motion": result["zero_motion"],
        "constant_velocity": result["constant_velocity"],
        "compass": result.get("compass"),
    }
    out["motion"] = result.get("motion")
    out["sequences"] = result["sequences"]
    out["meta"] = {
        k: result.get(k)
        for k in ("source", "data", "split", "split_name", "snippet", "stride", "out", "yaw_roll")
    }
    return out


def format_pose_table(result: dict[str, Any]) -> str:
    """A readable table of a result of :func:`evaluate_pose`: model and baselines, then the ratios
    model / baseline (below 1 is better), then the motion diagnostics and their verdict."""
    cols = POSE_TABLE_METRICS
    lines = [
        f"pose: {result['n_snippets']} snippets of {result['snippet']} frames (stride {result['stride']}), "
        f"{len(result['sequences'])} sequences ({result['source']}); metres and degrees, lower is better",
        text_row("", cols, 17, 26),
    ]
    rows: list[tuple[str, dict[str, Any]]] = [
        ("model", result["model"]),
        ("zero motion", result["zero_motion"]),
        ("constant velocity", result["constant_velocity"]),
    ]
    if result.get("compass") is not None:
        rows.append(("compass", result["compass"]))
    for name, m in rows:
        lines.append(text_row(name, [m.get(c) for c in cols], 17, 26))
    for name, m in rows[1:]:
        lines.append(
            text_row(f"model/{name}", [ratio(result["model"].get(c), m.get(c)) for c in cols], 17, 26)
        )
    if result.get("motion") is not None:
        lines += ["", format_motion_table(result["motion"])]
    return "\n".join(lines)
