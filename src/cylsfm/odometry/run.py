"""``cylsfm odometry``: a whole ride's trajectory from a trained model (see :mod:`cylsfm.odometry`)."""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._version import __version__
from ..atomic import atomic_write_text
from ..data.format import load_depth, save_depth
from ..data.io import write_tum
from ..errors import CylsfmError, InputError
from ..evaluate.pose_metrics import chain_poses
from ..geometry import Camera, load_camera
from ..geometry.ground import metric_scale, steady_height_steps
from ..geometry.photometric import resize_depth
from ..model import Predictor
from ..model.checkpoint import checkpoint_id
from ..model.plan import model_vfov_h, network_images, network_mask, plan_input
from ..runtime import fingerprint, progress_bar
from .closure import closed_steps, loop_line, loop_summary_of, ride_loops
from .frames import Ride, depth_files, open_ride
from .loops import Loop
from .report import ride_metrics, top_view
from .settings import LOOP_MIN_FRAMES, OdometrySettings
from .state import STATE_FILE, State
from .track import MOUNT_AGREEMENT, STRAIGHT_AHEAD_DEG, Tracker, TrackOptions, keyframe_steps, network_size

__all__ = ["OdometryResult", "OdometrySettings", "odometry"]

#: Frames read and processed between two saves of the state.
CHUNK = 32
#: Where depth maps wait in network units until the scale to metres is known.
RAW_DEPTH = ".odometry-depth"


@dataclass
class OdometryResult:
    """What :func:`odometry` wrote and measured.

    Attributes:
        trajectory: the TUM file (``OUT/trajectory.txt``).
        c2w: the camera-to-world poses ``[M,4,4]`` written there; ``times`` ``[M]``, ``frames`` their names.
        unit: ``"network units"`` or ``"metres"``; ``metres_per_unit`` the scale applied (``None``: none).
        metrics: measures against the ground truth (``None`` without it), as in ``OUT/metrics.json``.
        timings: seconds per part of the work; ``seconds`` in all.
        loops: what the loop closure found (as ``odometry.json``'s ``loops``; ``None``: not looked for).
    """

    trajectory: Path
    c2w: np.ndarray
    times: np.ndarray
    frames: list[str]
    unit: str
    metres_per_unit: float | None
    metrics: dict[str, Any] | None
    timings: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    loops: dict[str, Any] | None = None


def odometry(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str] | Predictor,
    out: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
) -> OdometryResult:
    """The trajectory of a whole ride: the pose network's steps chained, optionally refined by direct
    photometric alignment; see :mod:`cylsfm.odometry` for the method and the files written.

    Args:
        input: a video file, a folder of frames, or a dataset sequence directory.
        checkpoint: a checkpoint file, a run directory or a ready predictor.
        out: the output directory (created; a killed run in it is continued).
        settings: what to read and compute (:class:`OdometrySettings`; default: its defaults).

    Raises:
        CylsfmError: an input, camera, checkpoint or dataset problem, naming the file.
    """
    started = time.perf_counter()
    opt = settings or OdometrySettings()
    ride = open_ride(input, opt.fps, opt.stride)
    predictor, plan = _model_and_plan(ride, checkpoint, opt)
    net_cam = plan.network_input.resized(*predictor.size)
    mask_file = ride_mask(ride, opt.mask)
    mask = network_mask(mask_file, ride.size, plan, predictor.size) if mask_file is not None else None
    depths = _true_depth_files(opt.depth_from, ride, plan)
    turnable = _turnable(predictor, opt.mount_yaw)
    fixed = {
        "refine": opt.refine,
        "fps": opt.fps,
        "stride": opt.stride,
        "keyframe_every": opt.keyframe_every,
        "mount_yaw": opt.mount_yaw,
        "pose_iterations": predictor.pose_iterations,
        "networks": str(predictor.dtype or torch.float32),  # bf16 where native (amp), else fp32
        "ground_fit": opt.camera_height is not None,  # the depth of every frame is needed for it
        "mask": _file_id(mask_file),
        "loops": opt.loops,  # the loop settings are the loops' own key (closure.ride_loops)
    }
    run_settings = _settings(ride, checkpoint, plan, opt, fixed)
    (dest := Path(out)).mkdir(parents=True, exist_ok=True)
    state = State.load(dest / STATE_FILE, fingerprint(run_settings)) or State(fingerprint(run_settings))
    if not opt.find_mount and turnable:  # given: known from the start
        state.mount = (math.radians(float(opt.mount_yaw)), float("nan"), 0)
    depth_of = _depth_reader(depths, predictor, net_cam) if depths is not None else None
    writer = None
    if opt.save_depth_maps:
        writer = _depth_writer(dest / (RAW_DEPTH if opt.camera_height else "depth"), state)
    tracker = Tracker(
        predictor,
        net_cam,
        state,
        TrackOptions(
            refine=opt.refine,
            align=opt.align,
            batch_size=opt.batch_size,
            keyframe_every=opt.keyframe_every,
            need_depth=opt.camera_height is not None or opt.steady_height,
            find_mount=opt.find_mount and turnable,
            places=bool(opt.loops),
        ),
        depth_of=depth_of,
        on_depth=writer,
        mask=mask,
    )
    if opt.loops is True and not tracker.places:
        raise InputError(f"{ride.path}: loops need a model that reads full panoramas (this one reads a crop)")
    if not state.finished:
        _track(ride, plan, predictor, tracker, state, dest, opt.progress)
    loops = None
    if tracker.places and (opt.loops is True or state.next_frame >= LOOP_MIN_FRAMES):
        loops = ride_loops(ride, plan, predictor, tracker, state, opt, dest)
    masked = None if mask is None else {"file": str(mask_file), "occluded_fraction": float(1 - mask.mean())}
    return _finish(ride, state, dest, tracker, opt, depths, started, masked, loops)


def ride_mask(ride: Ride, mask: Any) -> Path | None:
    """The mask image to use: the one given, else a dataset sequence's own (``False``: none)."""
    if mask is False:
        return None
    if mask is not None:
        return Path(mask)
    return ride.sequence.mask if ride.sequence is not None else None


def _file_id(path: Path | None) -> str | None:
    """A file's path and content digest (what a saved state was computed with)."""
    if path is None:
        return None
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    except OSError as exc:
        raise CylsfmError(f"{path}: cannot read the mask ({exc.strerror or exc})") from None
    return f"{path.resolve()} {digest}"


def _true_depth_files(depth_from: Any, ride: Ride, plan: Any) -> list[Path] | None:
    """The ground-truth depth files of ``depth_from`` for the ride's frames (``None``: not asked for)."""
    if depth_from is None:
        return None
    if plan.convert_to is not None:
        raise CylsfmError(
            f"{ride.path}: ground-truth depth needs frames the model takes as they are (no conversion)"
        )
    return depth_files(depth_from, ride)


def _turnable(predictor: Predictor, mount_yaw: float | str) -> bool:
    """Whether the pose network can read turned frames (a full-panorama model); a direction of travel
    given for one that cannot is an error."""
    turnable = predictor.fov >= 360 and predictor.wrap
    if mount_yaw != "auto" and mount_yaw and not turnable:
        raise InputError(f"mount_yaw: a {predictor.fov:g}-degree model reads no other direction than its own")
    return turnable


def _model_and_plan(ride: Ride, checkpoint: Any, opt: OdometrySettings) -> tuple[Predictor, Any]:
    """The predictor (``checkpoint`` itself when it is one) and how the ride's frames reach it."""
    predictor = (
        checkpoint
        if isinstance(checkpoint, Predictor)
        else Predictor.from_checkpoint(checkpoint, opt.device, opt.pose_iterations, opt.amp)
    )
    return predictor, ride_plan(ride, predictor, opt.camera)


def _settings(
    ride: Ride, checkpoint: Any, plan: Any, opt: OdometrySettings, fixed: dict[str, Any]
) -> dict[str, Any]:
    """What decides a run's result: a saved state with other settings is not continued. (Depth maps are
    written in network units, or kept apart until the scale to metres is known: so that scale counts.)"""
    return {
        "input": str(Path(ride.path).resolve()),
        "checkpoint": _checkpoint_id(checkpoint),
        "camera": plan.network_input.to_dict(),
        "depth_from": str(Path(opt.depth_from).resolve()) if opt.depth_from is not None else None,
        **fixed,
        "depth_maps": opt.save_depth_maps,
        "depth_scale": opt.camera_height if opt.save_depth_maps else None,
        "align": asdict(opt.align),
        "version": __version__,
    }


def ride_plan(ride: Ride, predictor: Predictor, camera: Any) -> Any:
    """How the ride's frames reach the network (its camera: the one given, or a dataset sequence's own)."""
    cam = load_camera(camera) if isinstance(camera, str | os.PathLike) else camera
    cam_name = (
        str(camera) if isinstance(camera, str | os.PathLike) else ("the given camera" if camera else None)
    )
    if cam is None and ride.camera is not None:
        cam, cam_name = ride.camera, str(ride.path / "camera.json")
    plan = plan_input(ride.path, ride.size, predictor, model_vfov_h(predictor.config), cam, cam_name)
    if plan.note:
        print(f"{ride.path}: {plan.note}", file=sys.stderr)
    return plan


def _checkpoint_id(checkpoint: Any) -> str:
    if isinstance(checkpoint, Predictor):
        return f"predictor {id(checkpoint)}"
    return checkpoint_id(checkpoint)


def _depth_reader(files: list[Path], predictor: Predictor, camera: Camera):
    """Ground-truth depth of frame ``i`` ``[1,h,w]`` at the network's size, in the view it sees."""
    win = predictor.window(camera)

    def read(i: int) -> torch.Tensor:
        d = resize_depth(torch.from_numpy(load_depth(files[i]))[None, None], (camera.height, camera.width))
        return (d if win is None else d[..., win[0] : win[1]])[0]

    return read


def _depth_writer(folder: Path, state: State):
    folder.mkdir(parents=True, exist_ok=True)

    def write(indices: list[int], depth: torch.Tensor) -> None:
        for i, d in zip(indices, depth, strict=True):
            save_depth(folder / f"{state.stems[i]}.npy", d[0].cpu().numpy())

    return write


def _track(
    ride: Ride, plan: Any, predictor: Predictor, tracker: Tracker, state: State, dest: Path, progress: bool
) -> None:
    """Read the ride in chunks, push them through the tracker, save the state after each."""
    bar = progress_bar(total=ride.frames or None, desc="odometry", unit="frame", enabled=progress, leave=True)
    bar.update(state.next_frame)
    chunk: list[tuple[int, np.ndarray]] = []

    def flush() -> None:
        t = time.perf_counter()
        images = network_size(
            network_images([rgb for _, rgb in chunk], plan, predictor.device), predictor.size
        )
        tracker.times.add("frames to the network's size", t)
        tracker.push([i for i, _ in chunk], images)
        state.save(dest / STATE_FILE)
        bar.update(len(chunk))
        chunk.clear()

    t = time.perf_counter()
    try:
        for i, stem, when, rgb in ride.read(start=state.next_frame):
            if i < state.next_frame:
                continue
            if rgb is None:  # pragma: no cover - read() decodes every frame from start on
                raise CylsfmError(f"{ride.path}: frame {stem} was not decoded")
            state.stems.append(stem)
            state.times.append(when)
            chunk.append((i, rgb))
            t = tracker.times.add("decoding", t)
            if len(chunk) >= CHUNK:
                flush()
            t = time.perf_counter()
        if chunk:
            flush()
    finally:
        bar.close()
    m = state.next_frame
    need = int(predictor.window_length)
    if m < need:
        raise CylsfmError(f"{ride.path}: {m} frames; a trajectory needs at least {need}")
    tracker.finish(m)
    state.finished = True
    state.save(dest / STATE_FILE)


def _finish(
    ride: Ride,
    state: State,
    dest: Path,
    tracker: Tracker,
    opt: OdometrySettings,
    depths: list[Path] | None,
    started: float,
    masked: dict[str, Any] | None,
    loops: list[Loop] | None,
) -> OdometryResult:
    """Close the loops, scale, chain, and write the trajectory, the plot, the measures and the summary."""
    refine = opt.refine
    refined = keyframe_steps(np.stack(state.refined), tracker.every) if refine else None
    odometry_steps = _steady(refined if refined is not None else np.stack(state.net), state, opt)
    closed = closed_steps(odometry_steps, loops, tracker.times)
    steps, unit, scale, comments = _in_unit(
        closed if closed is not None else odometry_steps, state, opt, depths
    )
    if scale is not None and opt.save_depth_maps:
        _scaled_depth(dest, state, scale)
    comments.append(f"cylsfm {__version__} odometry of {ride.path}{_how(opt)}")
    if masked is not None:
        comments.append(f"mask: {masked['file']} ({masked['occluded_fraction']:.1%} of the pixels left out)")
    if (mount := _mount_summary(state)) is not None:
        comments.append(f"direction of travel in the panorama: {mount['yaw_deg']:.1f} deg ({mount['how']})")
    loop_summary = loop_summary_of(loops)
    if loop_summary is not None:
        comments.append(loop_line(loop_summary))
    c2w = chain_poses(steps)
    times = np.asarray(state.times)
    write_tum(dest / "trajectory.txt", times, c2w, comments)
    if refine:
        write_tum(
            dest / "trajectory_network.txt",
            times,
            chain_poses(np.stack(state.net)),
            ["the pose network alone"],
        )
    steady = odometry_steps if opt.steady_height and refined is not None else None
    measured = _measure(ride, state, refined, closed, steady)
    top_view(
        dest / "trajectory.png",
        c2w,
        "m" if scale or depths is not None else "network units",
        measured.truth if measured else None,
        measured.curves if measured else {},
        links=[(lp.i, lp.j) for lp in loops or [] if lp.accepted],
    )
    seconds = time.perf_counter() - started
    summary = {
        "input": str(ride.path),
        "frames": len(c2w),
        "unit": unit,
        "metres_per_unit": scale,
        "refined": refine,
        "steady_height": opt.steady_height,
        "seconds": seconds,
        "frames_per_second": len(c2w) / seconds if seconds > 0 else None,
        "timings": tracker.times.parts,
        "refinement": _refine_stats(state) if refine else None,
        "direction_of_travel": _mount_summary(state),
        "mask": masked,
        "loops": loop_summary,
    }
    atomic_write_text(dest / "odometry.json", json.dumps(summary, indent=2) + "\n")
    if measured:
        atomic_write_text(dest / "metrics.json", json.dumps(measured.metrics, indent=2) + "\n")
    return OdometryResult(
        trajectory=dest / "trajectory.txt",
        c2w=c2w,
        times=times,
        frames=list(state.stems),
        unit=unit,
        metres_per_unit=scale,
        metrics=measured.metrics if measured else None,
        timings=tracker.times.parts,
        seconds=seconds,
        loops=loop_summary,
    )


def _steady(steps: np.ndarray, state: State, opt: OdometrySettings) -> np.ndarray:
    """``steps [M-1,4,4]``, their lengths in a steady camera height's unit when ``opt.steady_height``."""
    return steady_height_steps(steps, np.asarray(state.heights))[0] if opt.steady_height else steps


def _how(opt: OdometrySettings) -> str:
    """The trajectory header's account of how the steps were made."""
    return (", refined by direct alignment" if opt.refine else "") + (
        ", steady camera height" if opt.steady_height else ""
    )


def _in_unit(
    steps: np.ndarray, state: State, opt: OdometrySettings, depths: list[Path] | None
) -> tuple[np.ndarray, str, float | None, list[str]]:
    """The steps ``[M-1,4,4]`` in metres when the camera height is given (the ground fitted in every
    frame), else as they are: ``(steps, unit, metres per network unit or None, the file's unit line)``."""
    if opt.camera_height is None:
        unit = "metres (ground-truth depth)" if depths is not None else "network units"
        hint = "" if depths is not None else " (give the camera height for metres)"
        return steps, unit, None, [f"unit: {unit}{hint}"]
    scale, used = metric_scale(np.asarray(state.heights), opt.camera_height)
    steps = steps * np.where(np.arange(4)[:, None] < 3, [1.0, 1.0, 1.0, scale], 1.0)  # translations in m
    line = (
        f"unit: metres (camera height {opt.camera_height:g} m over the ground fitted in {used} frames: "
        f"{scale:.6g} m per network unit)"
    )
    return steps, "metres", scale, [line]


def _mount_summary(state: State) -> dict[str, Any] | None:
    """The direction of travel the pose network was turned to (``None``: the frames as they are)."""
    yaw, agreement, pairs = state.mount
    if not math.isfinite(yaw):
        return None
    if not pairs:
        how = "given"
    elif math.isfinite(agreement) and yaw == 0.0 and agreement < MOUNT_AGREEMENT:
        how = f"not found: {pairs} pairs of frames disagree ({agreement:.0%} agree); taken as straight ahead"
    else:
        how = f"found in {pairs} pairs of frames, {agreement:.0%} agree"
        if abs(math.degrees(yaw)) < STRAIGHT_AHEAD_DEG:
            how += f"; within {STRAIGHT_AHEAD_DEG:g} degrees of straight ahead, the frames not turned"
    return {
        "yaw_deg": math.degrees(yaw),
        "agreement": agreement if pairs else None,
        "pairs": pairs,
        "how": how,
    }


def _refine_stats(state: State) -> dict[str, float]:
    cost = np.asarray(state.cost)
    return {
        "start_cost_mean": float(cost[:, 0].mean()),
        "cost_mean": float(cost[:, 1].mean()),
        "compass_start_fraction": float((cost[:, 2] == 1).mean()),
        "valid_fraction_mean": float(cost[:, 3].mean()),
    }


@dataclass
class _Measured:
    """The measures against the ground truth (as ``metrics.json``), the aligned curves for the top view
    and the true camera-to-world poses ``[M,4,4]``."""

    metrics: dict[str, Any]
    curves: dict[str, Any]
    truth: np.ndarray


def _measure(
    ride: Ride,
    state: State,
    refined: np.ndarray | None,
    closed: np.ndarray | None,
    steady: np.ndarray | None,
) -> _Measured | None:
    truth = ride.ground_truth()
    if truth is None:
        return None
    times, gt = truth
    if len(gt) != len(state.stems):
        return None
    steps = {
        "loops closed": closed,
        "steady height": steady,
        "refined": refined,
        "network": np.stack(state.net),
        "compass": np.stack(state.compass),
    }
    metrics, curves = ride_metrics(times, gt, steps)
    return _Measured(metrics, curves, gt)


def _scaled_depth(dest: Path, state: State, scale: float) -> None:
    """``OUT/depth/FRAME.npy`` in metres from the maps in network units (idempotent; the raw maps are
    removed once every scaled one is written)."""
    raw, folder = dest / RAW_DEPTH, dest / "depth"
    if not state.rescaled:
        folder.mkdir(parents=True, exist_ok=True)
        for stem in state.stems:
            save_depth(folder / f"{stem}.npy", load_depth(raw / f"{stem}.npy") * np.float32(scale))
        state.rescaled = 1
        state.save(dest / STATE_FILE)
    shutil.rmtree(raw, ignore_errors=True)
