"""The bundle-adjustment stage of :func:`cylsfm.odometry` (by default with ``refine``; ``--no-bundle``):
after the loops are closed, every frame's SIFT features at its own resolution and in its own geometry
(off the mask), matches between each frame and the next few guided by the odometry, tracks, and
:func:`~cylsfm.odometry.bundle.adjust.bundle_adjust` of the poses and points, seeded and held by the
odometry's steps (its scale kept: the scale stage then brings it to metres as before).

Each consecutive pair's relative pose is first corrected from its own matches
(:func:`~cylsfm.odometry.bundle.matching.relative_pose`: the rotation and the direction of travel, the
odometry's step length kept) where it has at least ``min_matches``; the corrected ride is both the
adjustment's start and its step priors. Started from the odometry itself, a few degrees off a step
leave the adjustment in a wrong minimum (docs/results/bundle-adjustment.md).

The frames of every accepted loop are matched as well, guided by the loop's own relative pose, so that
their tracks join the two visits and the adjustment holds the ride together where it comes back. A loop
whose two frames share too few matches (:func:`_confirms`) is not confirmed by the features: a place that
only looks like another (the direct alignment can take a repeated facade for the same one). It is left
out, and the adjustment starts from the ride closed by the other loops alone. A true revisit shares
hundreds (352 and 649 on the loop ride at 512x128); a false loop accepted on a 1000-frame ride, 4.

The result is kept in the run's state with the fingerprint of the stage's settings and of the steps it
started from: a run continued or run again the same way adjusts nothing again; one killed during the
stage does it again (the tracking and the loops are kept).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...data.io import load_mask
from ...evaluate.pose_metrics import chain_poses
from ...geometry import invert
from ...geometry.bearings import pixel_bearings
from ...runtime import fingerprint, progress_bar
from .adjust import BundleSettings, bundle_adjust
from .features import Features, detect
from .matching import match_pair, own_nearest, relative_pose, tracks_of

if TYPE_CHECKING:
    from ..job import Job
    from ..loops.loop import Loop
    from ..state import State

__all__ = ["METHOD", "Bundled", "RideBundleSettings", "adjust_ride"]

#: The stage's method, in its fingerprint: raised when the same settings would give another result (2: guided
#: matching, the quarter pixel taken off; 3: no keypoint on an occluder's outline; 4: loops confirmed by
#: their matches), so that a run's saved adjustment of an older method is done again.
METHOD = 4

#: A loop is confirmed by at least ``min_matches`` matches, or by this share of the features of the poorer
#: of its two frames: true revisits share 24-100% (128x32 room, 90 features a frame) and 34-63% (512x128,
#: 1000), a false loop on a 1000-frame ride 0.4%.
LOOP_SHARE = 0.2


@dataclass(frozen=True)
class RideBundleSettings:
    """How a ride is adjusted.

    Attributes:
        span: each frame is matched with the next ``span`` frames.
        features: SIFT keypoints a frame at most (the strongest). At 1024x512 about 5500 are found and
            all are kept (the strongest 4000 measured worse, docs/results/bundle-adjustment.md); at
            512x128 about 1000.
        contrast: SIFT's contrast threshold (lower finds more, weaker keypoints; OpenCV's default is 0.04,
            COLMAP's about 0.02 in OpenCV's terms). 0.01 measured best at 512x128 (finer steps); the
            ``features`` strongest are kept, so on well-textured frames it rarely binds.
        ratio: Lowe's ratio of the descriptor matches.
        max_epipolar_deg: a match's largest angle off the odometry's epipolar plane.
        min_matches: a consecutive pair's relative pose is corrected from its matches when it has this
            many; else the odometry's step is kept.
        adjust: the adjustment's own settings.
    """

    span: int = 4
    features: int = 8000
    contrast: float = 0.01
    ratio: float = 0.8
    max_epipolar_deg: float = 2.0
    min_matches: int = 30
    adjust: BundleSettings = field(default_factory=BundleSettings)


@dataclass
class Bundled:
    """What the stage gave.

    Attributes:
        steps: the adjusted consecutive steps ``T_{j->j+1}`` ``[M-1,4,4]``, in the odometry's unit.
        summary: counts (features a frame, tracks, observations, kept, rounds) and the seconds of each part
            (features, matching, relative poses, adjustment) for ``odometry.json``.
        key: the fingerprint of the settings it was made with.
        seconds: the time it took (0 when the state had it: ``fresh`` is then ``False``).
        points: the triangulated points kept ``[P,3]``, in the first frame's world and the odometry's unit,
            and their colours ``uint8 [P,3]`` (of a frame that sees each).
        tracks: their observations kept ``[N,4]``: frame, point (an index into ``points``) and the
            keypoint ``(u, v)`` in the frame's own pixels.
    """

    steps: np.ndarray
    summary: dict
    key: str
    seconds: float
    points: np.ndarray
    colours: np.ndarray
    tracks: np.ndarray
    fresh: bool = True


def adjust_ride(
    job: Job,
    state: State,
    steps: np.ndarray,
    loops: Sequence[Loop] = (),
    close: Callable[[list[Loop]], np.ndarray | None] | None = None,
) -> Bundled:
    """Adjust the ride whose odometry has steps ``steps [M-1,4,4]``, before any loop is closed (see the
    module docstring).

    Args:
        loops: the accepted loops; their frames are matched too, and those that the matches confirm hold
            the ride together where it comes back.
        close: the pose graph: the steps closed by the loops given (``None`` for none); the adjustment
            starts from the steps closed by the confirmed loops. ``None``: start from ``steps``.
    """
    settings = job.settings.bundle_settings
    # the settings, the method and the odometry it starts from (other loops, another seed: adjusted again)
    seed = hashlib.sha256(b"".join([steps.tobytes(), *(np.asarray(lp.pose).tobytes() for lp in loops)]))
    seed = seed.hexdigest()
    pairs = sorted((lp.i, lp.j) for lp in loops)
    key = fingerprint({"settings": asdict(settings), "method": METHOD, "seed": seed, "loops": pairs})
    if state.bundle_key == key and len(state.bundled) == len(steps):
        saved = state.bundle_points
        return Bundled(
            np.stack(state.bundled),
            dict(state.bundle_summary),
            key,
            0.0,
            saved[:, :3],
            saved[:, 3:].astype(np.uint8),
            state.bundle_tracks,
            fresh=False,
        )
    started = time.perf_counter()
    camera = job.plan.camera  # the frames' own
    feats, bearings = _features(job, settings, len(steps) + 1)
    clock = {"features": time.perf_counter() - started}
    c2w, matches, confirmed = _matches(settings, feats, bearings, steps, loops, close)
    obs = tracks_of(matches, bearings)
    clock["matching"] = time.perf_counter() - started - sum(clock.values())
    pixel = 1.0 / float(camera.fx)
    seed = _corrected(c2w, matches, bearings, settings.min_matches, 2.0 * settings.adjust.pixel_sigma * pixel)
    clock["relative poses"] = time.perf_counter() - started - sum(clock.values())
    done = bundle_adjust(seed, obs, pixel, settings.adjust)
    clock["adjustment"] = done.seconds
    adjusted = np.stack([invert(done.c2w[j + 1]) @ done.c2w[j] for j in range(len(c2w) - 1)])
    kept = np.isfinite(done.points[:, 0]) if obs.points else np.zeros(0, dtype=bool)
    colours = np.zeros((obs.points, 3), np.uint8)
    if obs.points:  # each point's colour where its first observation sees it
        flat = np.concatenate([f.colours for f in feats])
        colours[obs.point[::-1]] = flat[obs.keypoint[::-1]]
    summary = {
        "features_per_frame": float(np.mean([len(f) for f in feats])),
        "tracks": int(obs.points),
        "points": int(np.isfinite(done.points[:, 0]).sum()) if obs.points else 0,
        "observations": len(obs.frame),
        "kept": int(done.inliers.sum()),
        "rounds": done.rounds,
        "loops_confirmed": len(confirmed),
        "loops_unconfirmed": len(loops) - len(confirmed),
        "loop_matches": sum(len(matches[(lp.i, lp.j)]) for lp in confirmed),
        **{f"{part.replace(' ', '_')}_seconds": round(t, 3) for part, t in clock.items()},
    }
    tracks = _tracks(obs, done.inliers, kept, feats)
    seconds = time.perf_counter() - started
    return Bundled(adjusted, summary, key, seconds, done.points[kept], colours[kept], tracks)


def _matches(
    settings: RideBundleSettings,
    feats: list[Features],
    bearings: list[np.ndarray],
    steps: np.ndarray,
    loops: Sequence[Loop],
    close: Callable[[list[Loop]], np.ndarray | None] | None,
) -> tuple[np.ndarray, dict, list[Loop]]:
    """The ride's start ``c2w [M,4,4]`` (``steps`` closed by the confirmed loops), the matches ``{(i, j):
    [K,2]}`` of each frame with the next ``span`` frames (guided by that start) and of each confirmed
    loop (by its own relative pose), and the confirmed loops."""
    own = [own_nearest(f.descriptors) for f in feats]  # each keypoint's look-alike in its own frame

    def matched(i: int, j: int, rel: np.ndarray) -> np.ndarray:  # guided by rel = T_{i->j}
        b = (bearings[i], bearings[j])
        return match_pair(
            feats[i], feats[j], *b, rel, settings.ratio, settings.max_epipolar_deg, own_b=own[j]
        )

    found = {(lp.i, lp.j): matched(lp.i, lp.j, lp.pose) for lp in loops}
    confirmed = [lp for lp in loops if _confirms(found[(lp.i, lp.j)], feats[lp.i], feats[lp.j], settings)]
    closed = close(confirmed) if close is not None and confirmed else None
    c2w = chain_poses(closed if closed is not None else steps)
    matches = {(lp.i, lp.j): found[(lp.i, lp.j)] for lp in confirmed}
    for i in range(len(c2w)):
        for j in range(i + 1, min(len(c2w), i + 1 + settings.span)):
            matches[(i, j)] = matched(i, j, invert(c2w[j]) @ c2w[i])
    return c2w, matches, confirmed


def _confirms(matches: np.ndarray, a: Features, b: Features, settings: RideBundleSettings) -> bool:
    """Whether a loop's ``matches [K,2]`` between frames of features ``a`` and ``b`` show the same place:
    ``min_matches`` of them, or :data:`LOOP_SHARE` of the poorer frame's features (a small frame has
    few)."""
    return len(matches) >= min(settings.min_matches, LOOP_SHARE * min(len(a), len(b)))


def _tracks(obs, inliers: np.ndarray, kept: np.ndarray, feats: list[Features]) -> np.ndarray:
    """The observations ``[N,4]`` (frame, point renumbered among the ``kept`` ones, keypoint u, v) that the
    adjustment kept."""
    if not obs.points:
        return np.zeros((0, 4))
    use = inliers & kept[obs.point]
    renumbered = np.cumsum(kept) - 1
    uv = np.concatenate([f.uv for f in feats])[obs.keypoint[use]]
    return np.column_stack([obs.frame[use], renumbered[obs.point[use]], uv]).astype(np.float64)


def _corrected(
    c2w: np.ndarray, matches: dict, bearings: list[np.ndarray], min_matches: int, scale: float
) -> np.ndarray:
    """The ride ``c2w [M,4,4]`` with each consecutive step's rotation and direction corrected from its
    matches (at least ``min_matches``; ``scale``: the robust loss's, radians)."""
    out = [c2w[0]]
    for j in range(len(c2w) - 1):
        step = invert(c2w[j + 1]) @ c2w[j]  # T_{j->j+1}
        pairs = matches.get((j, j + 1), np.zeros((0, 2), np.int64))
        if len(pairs) >= min_matches:
            step = relative_pose(bearings[j][pairs[:, 0]], bearings[j + 1][pairs[:, 1]], step, scale)
        out.append(out[-1] @ invert(step))
    return np.stack(out)


def _features(job: Job, settings: RideBundleSettings, m: int) -> tuple[list[Features], list[np.ndarray]]:
    """Every frame's features and their bearings ``[K,3]`` in the frames' own camera."""
    camera = job.plan.camera
    mask = None if job.mask_file is None else load_mask(job.mask_file, job.ride.size)
    feats, bearings = [], []
    bar = progress_bar(total=m, desc="features", unit="frame", enabled=job.settings.progress, leave=False)
    try:
        for i, _, _, rgb in job.ride.read():
            if i >= m:
                break
            f = detect(rgb, camera.wraps, mask, settings.features, settings.contrast)
            feats.append(f)
            uv = torch.from_numpy(f.uv)
            bearings.append(pixel_bearings(camera, uv).numpy() if len(f) else np.zeros((0, 3)))
            bar.update(1)
    finally:
        bar.close()
    return feats, bearings
