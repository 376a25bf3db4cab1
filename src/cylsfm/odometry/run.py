"""``cylsfm odometry``: a whole ride's trajectory from a trained model (see :mod:`cylsfm.odometry`).

The run is resolved once into a :class:`~cylsfm.odometry.job.Job` (settings, networks, how the frames
reach them, mask, depth source, fingerprints) and goes through named stages, each a module with one job:

1. **track** (:mod:`~cylsfm.odometry.track`): depth, the pose network's steps, the compass and the
   refinement, frame by frame, saved chunk by chunk (a killed run continues);
2. **find loops** (:mod:`~cylsfm.odometry.loops.search`): the places the ride comes back to;
3. **steady height** (:func:`~cylsfm.odometry.scale.steady_steps`), then **close the pose graph**
   (:func:`~cylsfm.odometry.loops.graph.closed_steps`) with the accepted loops;
   **bundle adjustment** (``bundle``, :mod:`~cylsfm.odometry.bundle.stage`): poses and sparse points
   adjusted to SIFT features matched across frames;
4. **scale** (:mod:`~cylsfm.odometry.scale`): metres from the camera height; the depth files in the
   trajectory's unit, each frame's brought to the adjusted points it sees;
5. **write** (:mod:`~cylsfm.odometry.write`): the trajectory, the top view, the measures, the summary.

Each stage returns data (steps, loops with their reason codes, its seconds); the saved progress is the
:class:`~cylsfm.odometry.state.State`, which holds no setting.
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..model import Predictor
from .bundle.stage import adjust_ride
from .job import Job, resolve_job
from .loops import closed_steps, find_loops
from .points import write_points
from .scale import scale_depth_maps, scale_steps, steady_steps
from .settings import OdometrySettings
from .state import STATE_FILE, State
from .track import track
from .write import OdometryResult, Steps, write_outputs

__all__ = ["OdometryResult", "OdometrySettings", "odometry", "run_job"]


def odometry(
    input: str | os.PathLike[str],
    checkpoint: str | os.PathLike[str] | Predictor,
    out: str | os.PathLike[str],
    settings: OdometrySettings | None = None,
) -> OdometryResult:
    """The trajectory of a whole ride: the pose network's steps chained, optionally refined by direct
    photometric alignment, loops closed; see :mod:`cylsfm.odometry` for the method and the files written.

    Args:
        input: a video file, a folder of frames, or a dataset sequence directory.
        checkpoint: a checkpoint file, a run directory or a ready predictor.
        out: the output directory (created; a killed run in it is continued).
        settings: what to read and compute (:class:`OdometrySettings`; default: its defaults).

    Raises:
        CylsfmError: an input, camera, checkpoint or dataset problem, naming the file.
    """
    started = time.perf_counter()
    return run_job(resolve_job(input, checkpoint, out, settings), started)


def run_job(job: Job, started: float | None = None) -> OdometryResult:
    """Run a resolved job through the stages (see the module docstring) into ``job.out``; ``started``:
    when the run began (:func:`time.perf_counter`; default now), for the seconds it reports."""
    started = time.perf_counter() if started is None else started
    opt = job.settings
    job.out.mkdir(parents=True, exist_ok=True)
    state = State.load(job.out / STATE_FILE, job.state_key) or State(job.state_key)
    tracked = track(job, state)
    timings = dict(tracked.timings)
    loops = None
    if job.loops_wanted(state.next_frame):
        search = find_loops(job, state, tracked.steps)
        loops = search.loops
        if search.fresh:
            state.loops, state.loop_key = search.loops, search.key
            state.save(job.out / STATE_FILE)
            timings["loops"] = search.seconds
    odometry_steps = steady_steps(tracked.steps, np.asarray(state.heights), opt.steady_height)
    t = time.perf_counter()
    closed = closed_steps(odometry_steps, loops)
    if closed is not None:
        timings["pose graph"] = time.perf_counter() - t
    seed = closed if closed is not None else odometry_steps
    bundled = None
    if opt.adjusts:  # from the odometry and the loops that its features confirm, closed again by the graph
        accepted = [lp for lp in loops or [] if lp.accepted]

        def close(kept: list) -> np.ndarray | None:  # the graph closed above, when every loop is kept
            return closed if len(kept) == len(accepted) else closed_steps(odometry_steps, kept)

        bundled = adjust_ride(job, state, odometry_steps, accepted, close)
    if bundled is not None and bundled.fresh:
        state.bundled, state.bundle_summary, state.bundle_key = (
            list(bundled.steps),
            bundled.summary,
            bundled.key,
        )
        state.bundle_points = np.hstack((bundled.points, bundled.colours.astype(np.float64)))
        state.bundle_tracks = bundled.tracks
        state.save(job.out / STATE_FILE)
        timings["bundle adjustment"] = bundled.seconds
    scaled = scale_steps(job, state, bundled.steps if bundled is not None else seed)
    steps = Steps(
        network=np.stack(state.net),
        compass=np.stack(state.compass),
        refined=tracked.steps if opt.refine else None,
        steady=odometry_steps if opt.steady_height and opt.refine else None,
        closed=closed,
        adjusted=bundled.steps if bundled is not None else None,
    )
    bundle = bundled.summary if bundled is not None else None
    sparse = None
    if bundled is not None:  # the points in the trajectory's unit
        points = bundled.points * (scaled.metres_per_unit or 1.0)
        sparse = write_points(job.out, points, bundled.colours, bundled.tracks, scaled.unit)
    depth_scale = scale_depth_maps(job, state, scaled, sparse)
    seconds = time.perf_counter() - started
    return write_outputs(job, state, steps, scaled, loops, bundle, timings, seconds, depth_scale)
