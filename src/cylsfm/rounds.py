"""Training that learns from its rides' own geometry, without labels (``cylsfm train --sfm-rounds N``).

Self-supervision by view synthesis sees pairs of nearby frames. The bundle adjustment of
:func:`cylsfm.odometry` sees a whole ride: its poses and sparse points are far more precise than the
networks' and share one scale along the ride. So a run trains in stages over one run directory:

1. plain self-supervised training for ``sfm.first_share`` of the budget;
2. ``sfm.rounds`` times:

   a. **geometry**: the odometry, with the bundle adjustment, of every training ride with the networks
      as they are, into ``RUN/geometry/round_K/<ride>/`` (``trajectory.txt``, ``points.npz``);
   b. **training** on from the checkpoint with those rides as targets (:mod:`cylsfm.data.geometry`):
      the depth at the adjusted points (``loss.sfm_depth_weight``), the pose network towards the adjusted
      poses (``loss.sfm_pose_weight``), with ``sfm.dense_weight`` every frame's depth towards its fusion
      with its neighbours' by the adjusted poses (``loss.sfm_dense_weight``; the odometry then writes
      each frame's depth in the ride's one scale), and, with ``sfm.synthesis``, the sources warped by the
      adjusted poses; every photometric term is kept.

The budget (``minutes``, or ``max_steps``) covers everything, the odometry included: the time left after
each geometry pass is shared among the training stages left, less the passes still to come (each taken
to last as long as the last one). What is done is recorded in ``RUN/rounds.json`` (written atomically):
a run interrupted anywhere continues with ``--resume`` where it stopped (a training stage from its
checkpoint, a geometry pass ride by ride), with the configuration recorded when it started, to the same
result.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

from .atomic import atomic_write_text
from .data import build_index
from .data.strips import is_strip_dataset
from .errors import CylsfmError
from .model.config import TrainConfig, config_from_dict, config_to_dict
from .odometry import OdometrySettings, odometry
from .train.trainer import train

__all__ = ["STATE_FILE", "geometry_dir", "train_rounds"]

#: What a run with rounds has done, in its run directory.
STATE_FILE = "rounds.json"


def train_rounds(
    cfg: TrainConfig,
    run_dir: str | os.PathLike[str],
    resume: bool = False,
    progress: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train ``cfg`` in rounds over its rides' own geometry (see the module docstring).

    Args:
        cfg: the run's configuration; ``cfg.sfm`` says how many rounds and how they weigh.
        run_dir: the run directory (checkpoints, the geometry, ``rounds.json``).
        resume: continue the run there (from ``rounds.json``: its recorded configuration, what it did);
            ``overwrite``: start it again (its geometry, checkpoints and logs removed).
        progress: progress bars.

    Returns:
        ``{"steps", "seconds", "stages": [{"stage", "seconds", ...}], "run_dir"}``.
    """
    run = Path(run_dir)
    cfg, state = _start(cfg, run, resume, overwrite)
    plan = _stages(cfg.sfm.rounds)
    trained = [s["steps"] for s in state["stages"] if s["stage"] == "train"]
    steps = trained[-1] if trained else 0
    for k, stage in enumerate(plan):
        if k < len(state["stages"]):
            continue  # done before the run was interrupted
        if stage == "geometry" and _out_of_time(cfg, state):
            state["stopped"] = "minutes"  # no time left for another pass and its training
            _save_state(run, state)
            break
        started = time.monotonic()
        if stage == "train":
            sub = _training_config(cfg, run, state, plan, k)
            # the first stage starts afresh, unless it is resumed from its checkpoint
            fresh = k == 0 and not (resume and (run / "checkpoints" / "latest.pt").exists())
            clear = fresh and (
                overwrite or resume
            )  # an older run's outputs, or this one's before a checkpoint
            summary = train(sub, run, resume=not fresh, progress=progress, overwrite=clear)
            record = {"stage": "train", "steps": summary["steps"], "stopped": summary["stopped"]}
            steps = summary["steps"]
            if summary["stopped"] == "interrupted":
                state["seconds"] += time.monotonic() - started
                _save_state(run, state)
                return _summary(run, state, steps, interrupted=True)
        else:
            record = {"stage": "geometry", "rides": _geometry(cfg, run, _round_of(plan, k), progress)}
        record["seconds"] = round(time.monotonic() - started, 1)
        state["stages"].append(record)
        state["seconds"] += time.monotonic() - started
        _save_state(run, state)
    return _summary(run, state, steps)


def _start(cfg: TrainConfig, run: Path, resume: bool, overwrite: bool) -> tuple[TrainConfig, dict]:
    """The whole run's configuration and its record: on ``resume`` both as recorded when it started (the
    stages' own ``RUN/config.yaml`` hold their shares of the budget; the data root, the device and the
    loader processes may change); otherwise a new record, an older run in rounds refused or, with
    ``overwrite``, removed with its geometry."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise CylsfmError("--sfm-rounds runs the odometry between its stages: train it in one process")
    if is_strip_dataset(Path(cfg.data.root)):
        raise CylsfmError(
            f"{cfg.data.root}: --sfm-rounds needs a dataset of format v1 (rides with their frames)"
        )
    state = _load_state(run) if resume else None
    if state is not None:
        recorded = config_from_dict(state["config"], f"{run / STATE_FILE} (config)", saved=True)
        data = replace(recorded.data, root=cfg.data.root, workers=cfg.data.workers)
        return replace(recorded, data=data, device=cfg.device), state
    if resume:
        raise CylsfmError(f"{run / STATE_FILE}: not found: {run} is not a run in rounds to continue")
    held = [p for p in (STATE_FILE, "checkpoints", "metrics.jsonl", "tb") if (run / p).exists()]
    if held and not overwrite:
        raise CylsfmError(
            f"{run}: already holds a run ({', '.join(held)}): --resume continues it, --overwrite starts it again"
        )
    shutil.rmtree(run / "geometry", ignore_errors=True)  # an older run's (the trainer removes the rest)
    state = {"config": config_to_dict(cfg), "stages": [], "seconds": 0.0}
    run.mkdir(parents=True, exist_ok=True)
    _save_state(run, state)
    return cfg, state


def _out_of_time(cfg: TrainConfig, state: dict) -> bool:
    """Whether the minutes left cannot pay for another geometry pass (as long as the last one)."""
    if cfg.minutes is None:
        return False
    passes = [s["seconds"] for s in state["stages"] if s["stage"] == "geometry"]
    return cfg.minutes * 60 - state["seconds"] <= (passes[-1] if passes else 0.0)


def _stages(rounds: int) -> list[str]:
    """``train``, then ``geometry`` and ``train`` for each round."""
    return ["train"] + ["geometry", "train"] * rounds


def _round_of(plan: list[str], k: int) -> int:
    """The round (1, 2 ...) that stage ``k`` belongs to (0: the plain training)."""
    return plan[: k + 1].count("geometry")


def geometry_dir(run: Path, round_: int) -> Path:
    """Where round ``round_``'s geometry of the rides is written."""
    return run / "geometry" / f"round_{round_}"


def _training_config(cfg: TrainConfig, run: Path, state: dict, plan: list[str], k: int) -> TrainConfig:
    """The configuration of training stage ``k``: its share of the budget and, after a geometry pass, the
    rides' geometry as targets."""
    sfm = cfg.sfm
    trainings = plan.count("train")
    done = plan[:k].count("train")
    steps = cfg.max_steps
    if trainings > 1:  # the first share, then the rest in equal parts
        first = min(
            max(round(cfg.max_steps * sfm.first_share), 1), cfg.max_steps
        )  # a checkpoint to start from
        steps = first if k == 0 else first + round((cfg.max_steps - first) * done / (trainings - 1))
    minutes = cfg.minutes
    if minutes is not None and trainings > 1:
        if k == 0:  # less what a resumed first stage spent already
            minutes = max(minutes * sfm.first_share - state["seconds"] / 60, 0.0) or 1e-6
        else:
            passes = [s["seconds"] for s in state["stages"] if s["stage"] == "geometry"]
            left = minutes * 60 - state["seconds"] - passes[-1] * plan[k:].count("geometry")
            minutes = max(left / 60 / (trainings - done), 0.0) or 1e-6
    out = replace(cfg, max_steps=steps, minutes=minutes)
    if k == 0:
        return out
    data = replace(cfg.data, geometry=str(geometry_dir(run, _round_of(plan, k))))
    loss = replace(
        cfg.loss,
        sfm_depth_weight=sfm.depth_weight,
        sfm_pose_weight=sfm.pose_weight,
        sfm_dense_weight=sfm.dense_weight,
        sfm_synthesis=sfm.synthesis,
    )
    return replace(out, data=data, loss=loss)


def _geometry(cfg: TrainConfig, run: Path, round_: int, progress: bool) -> dict[str, str]:
    """The odometry with the bundle adjustment of every training ride into the round's folder, with the
    run's latest checkpoint; ``{ride: "ok" or why it has no geometry}``."""
    d = cfg.data
    index = build_index(d.root, d.split, d.split_name, d.seq_length, d.stride)
    out = geometry_dir(run, round_)
    settings = OdometrySettings(
        refine=cfg.sfm.refine,
        bundle=True,
        save_depth_maps=cfg.sfm.dense_weight > 0,  # in the ride's one scale: the fused targets' source
        progress=progress,
        mask=d.mask or None,
        device=cfg.device,
    )
    done: dict[str, str] = {}
    for s in index.used:
        seq = index.sequences[s]
        try:
            odometry(seq.path, run, out / seq.name, settings)
            done[seq.name] = "ok"
        except CylsfmError as exc:  # a ride too short or without features: trained on without targets
            shutil.rmtree(out / seq.name, ignore_errors=True)
            warnings.warn(f"{seq.path}: no geometry this round ({exc})", UserWarning, stacklevel=2)
            done[seq.name] = str(exc)
    return done


def _load_state(run: Path) -> dict | None:
    path = run / STATE_FILE
    if not path.exists():
        return None
    try:
        state = json.loads(path.read_text())
        if not isinstance(state.get("stages"), list) or not math.isfinite(float(state["seconds"])):
            raise ValueError("no stages or seconds")
        if not isinstance(state.get("config"), dict):
            raise ValueError("no configuration")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CylsfmError(f"{path}: not the record of a run in rounds ({exc})") from None
    return state


def _save_state(run: Path, state: dict) -> None:
    atomic_write_text(run / STATE_FILE, json.dumps(state, indent=1))


def _summary(run: Path, state: dict, steps: int, interrupted: bool = False) -> dict[str, Any]:
    return {
        "steps": steps,
        "seconds": state["seconds"],
        "stages": list(state["stages"]),
        "stopped": "interrupted" if interrupted else state.get("stopped", "done"),
        "run_dir": str(run),
    }
