"""The first stage of :func:`cylsfm.odometry`, tracking: depth for every frame, the pose network over every
window, each consecutive step from its window, the visual compass's yaw, and the refinement.

:func:`track` reads the ride in chunks and pushes them through a :class:`Tracker`
(:meth:`Tracker.push`); the tracker keeps only the few frames the next steps still need, and records
everything in a :class:`~cylsfm.odometry.state.State`, saved after each chunk, so that a run can stop
after any chunk and continue from it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ..errors import CylsfmError, ShapeError
from ..evaluate.pose_metrics import step_from_window, window_centre
from ..geometry import Camera, compass_yaw, invert, yaw_matrix
from ..geometry.align import AlignConfig, align
from ..geometry.ground import ground_height
from ..geometry.place import place_descriptor
from ..model import Predictor
from ..runtime import progress_bar
from .depth import RAW_DEPTH, DepthSource, depth_writer
from .mount import MOUNT_AGREEMENT, STRAIGHT_AHEAD_DEG, mount_yaw
from .state import STATE_FILE, State

if TYPE_CHECKING:
    from .job import Job

__all__ = ["CHUNK", "Timings", "TrackOptions", "Tracked", "Tracker", "keyframe_steps", "track"]

#: Frames read and processed between two saves of the state.
CHUNK = 32
#: ``(indices, view depths [B,1,h,w])`` -> written depth files.
DepthSink = Callable[[list[int], Tensor], None]


@dataclass
class Timings:
    """Seconds spent in each part of the work."""

    parts: dict[str, float] = field(default_factory=dict)

    def add(self, name: str, since: float) -> float:
        now = time.perf_counter()
        self.parts[name] = self.parts.get(name, 0.0) + now - since
        return now


@dataclass(frozen=True)
class TrackOptions:
    """What the :class:`Tracker` computes.

    Attributes:
        refine: refine each step by :func:`~cylsfm.geometry.align.align`, with ``align``'s settings.
        batch_size: windows / pairs per call.
        keyframe_every: refine each frame against a keyframe, a new one every this many frames (1: each
            frame against the one before).
        need_depth: predict every frame's depth (and fit the ground) even when nothing else needs it: for
            the metric scale. Without it, refinement or depth files, the pose network runs alone.
        find_mount: find the direction of travel in the panorama (:func:`~cylsfm.odometry.mount.mount_yaw`)
            from the first chunk, unless the state knows it; the pose network then reads every window turned
            so that the camera faces its motion (full panoramas only).
        places: record every frame's place descriptor and median depth (for loop closure; full
            panoramas only).
        mount_yaw: the direction of travel in the panorama, given (radians): the pose network reads every
            window turned so that the camera faces it; ``None``: found (``find_mount``) or none.
    """

    refine: bool = False
    align: AlignConfig = field(default_factory=AlignConfig)
    batch_size: int = 8
    keyframe_every: int = 1
    need_depth: bool = True
    find_mount: bool = False
    places: bool = False
    mount_yaw: float | None = None


class Tracker:
    """Depth, windows, steps and refinement over a stream of frames.

    Args:
        predictor: the networks.
        camera: the camera of the network-size frames given to :meth:`push` (``predictor.size``).
        state: where the results go (a new or a loaded state).
        options: what to compute.
        depth: every frame's depth (the network's, or ground truth); ``None``: the network's.
        on_depth: called with each chunk's indices and view depths (to write depth files).
        mask: ``[1,1,H,W]`` at the network's size (``predictor.size``): 1 where the scene is seen, 0 on an
            occluder fixed to the camera (a helmet, a mount), which the compass, the refinement and the
            search for the direction of travel leave out, and which the networks see filled from the
            pixels around it (:func:`~cylsfm.data.fill.fill_masked`); ``None``: every pixel.
    """

    def __init__(
        self,
        predictor: Predictor,
        camera: Camera,
        state: State,
        options: TrackOptions,
        depth: DepthSource | None = None,
        on_depth: DepthSink | None = None,
        mask: Tensor | None = None,
    ) -> None:
        self.p = predictor
        self.camera = camera
        self.view = predictor.network_camera(camera)
        self.window = predictor.window(camera)
        self.state = state
        self.refine = options.refine
        self.align_config = options.align
        self.batch = options.batch_size
        self.every = options.keyframe_every
        self.need_depth = options.need_depth or options.refine or on_depth is not None
        self.on_depth = on_depth
        self.given_mount = options.mount_yaw
        self.find_mount = options.find_mount and self.view.wraps
        self.places = options.places and self.view.wraps
        self.k = (int(predictor.window_length) - 1) // 2
        w, h = predictor.size
        if mask is not None and tuple(mask.shape) != (1, 1, h, w):
            raise ShapeError(f"mask must be [1,1,{h},{w}] (the network's size), got {tuple(mask.shape)}")
        self.mask = None if mask is None else mask.float().cpu()
        self.masked = {"mask": self.mask} if self.mask is not None else {}  # for the networks
        self.depth = depth if depth is not None else DepthSource(predictor, camera, self.mask)
        #: seconds spent in each part of the tracker's own work
        self.times = Timings()
        self.images: dict[int, Tensor] = {}
        self.depths: dict[int, Tensor] = {}
        for i, im, d in zip(state.tail_index, state.tail_images, state.tail_depths, strict=True):
            self.images[i] = torch.from_numpy(np.asarray(im, dtype=np.float32))
            self.depths[i] = torch.from_numpy(np.asarray(d, dtype=np.float32))

    # ------------------------------------------------------------------ the chunks
    def push(self, indices: list[int], images: Tensor) -> None:
        """Add frames ``indices`` (consecutive, the next ones) with their network-size images ``[B,3,H,W]``."""
        t = time.perf_counter()
        if self.need_depth:
            depth = self._depth(indices, images)
            t = self.times.add("depth", t)
            self.state.heights += ground_height(depth, self.view).tolist()
            if self.on_depth is not None:
                self.on_depth(indices, depth)
            t = self.times.add("ground, depth files", t)
        else:  # the network's poses alone need no depth
            depth = torch.zeros(len(indices), 1, 1, 1)
            self.state.heights += [float("nan")] * len(indices)
        if self.places:
            self.state.places += list(place_descriptor(self._view(images).cpu(), self._view_mask()).numpy())
            if self.need_depth:
                d = torch.where(depth > 0, depth, torch.full_like(depth, float("nan"))).flatten(1)
                self.state.reach += torch.nanmedian(d.cpu().float(), dim=1).values.tolist()
            else:
                self.state.reach += [float("nan")] * len(indices)
            t = self.times.add("place descriptors", t)
        if self.find_mount and self.given_mount is None and not math.isfinite(self.state.mount[0]):
            self._mount(indices, images, depth if self.need_depth else None)
            t = self.times.add("direction of travel", t)
        for i, im, d in zip(indices, images.cpu(), depth.cpu(), strict=True):
            self.images[i], self.depths[i] = im, d
        last = indices[-1]
        self._windows(last - self.k)
        self._steps(lambda j: max(j, self.k) <= last - self.k and j + 1 <= last, last + 1)
        self._forget()

    def finish(self, m: int) -> None:
        """Compute the last steps of a ride of ``m`` frames (its final windows are known now)."""
        self._steps(lambda j: j + 1 < m, m)
        self._forget(all_frames=True)

    # ------------------------------------------------------------------ the parts
    @property
    def roll(self) -> int:
        """Columns (of the network's input) by which the pose network's frames are turned: the direction
        of travel straight ahead (0 while it is not known, and when found within ``STRAIGHT_AHEAD_DEG``
        of it; a direction given is used as it is)."""
        if self.given_mount is not None:
            yaw = self.given_mount
        else:
            yaw = self.state.mount[0]
            if not math.isfinite(yaw) or abs(math.degrees(yaw)) < STRAIGHT_AHEAD_DEG:
                return 0
        return round(-yaw * self.p.size[0] / (2 * math.pi)) % self.p.size[0]

    def _mount(self, indices: list[int], images: Tensor, depth: Tensor | None) -> None:
        """Find the direction of travel in a chunk of frames (the first; nothing is changed for a chunk
        too short for it). Where the pairs disagree (a camera that hardly moved) it is taken as straight
        ahead."""
        k = self.k
        if images.shape[0] < 2 * k + 1:
            return
        if depth is None:
            depth = self._depth(indices, images)
        with torch.inference_mode():
            # the network's own depth of the targets serves the further passes (the frames not turned yet)
            given = depth[k : images.shape[0] - k] if self._passes_take_depth else None
            rel = self.p.ride_poses(images, self.camera, depth=given, **self.masked)
        length = float(rel[:, k, :3, 3].norm(dim=-1).median())  # the step after the target
        found = mount_yaw(images, depth, self.view, length, self.align_config, mask=self.mask)
        if found is not None:
            trusted = found.agreement >= MOUNT_AGREEMENT
            self.state.mount = (found.yaw if trusted else 0.0, found.agreement, found.pairs)
        if self.roll == 0 and k + len(self.state.windows) == indices[k]:
            # the frames stay as they are (a camera facing its motion): these are the chunk's windows
            self.state.windows += list(rel.double().cpu().numpy())

    def _depth(self, indices: list[int], images: Tensor) -> Tensor:
        return self.depth(indices, images)

    @property
    def _passes_take_depth(self) -> bool:
        """Whether the depth the tracker predicts (the network's, not ground truth) serves the pose
        network's further passes (there are some)."""
        return not self.depth.truth and self.p.pose_iterations > 0

    @property
    def _own_depth(self) -> bool:
        """Whether every frame's depth is predicted as it arrives and serves the further passes."""
        return self.need_depth and self._passes_take_depth

    def _windows(self, last_centre: int) -> None:
        """The pose network on every window whose centre is at most ``last_centre``."""
        k, st = self.k, self.state
        centres = list(range(k + len(st.windows), last_centre + 1))
        t = time.perf_counter()
        for n in range(0, len(centres), self.batch):
            chunk = centres[n : n + self.batch]
            frames = torch.stack([self.images[f] for f in range(chunk[0] - k, chunk[-1] + k + 1)])
            # the targets' depth, when predicted already, serves the pose network's further passes too
            depth = torch.stack([self.depths[c] for c in chunk]) if self._own_depth else None
            with torch.inference_mode():  # each pair of frames read once by the first pass
                rel = self.p.ride_poses(frames, self.camera, self.roll, depth=depth, **self.masked)
            st.windows += list(rel.double().cpu().numpy())
        self.times.add("pose network", t)

    def _view(self, x: Tensor) -> Tensor:
        return x if self.window is None else x[..., self.window[0] : self.window[1]]

    def _view_mask(self) -> Tensor | None:
        return None if self.mask is None else self._view(self.mask)

    def _steps(self, ready: Callable[[int], bool], m: int) -> None:
        """Every step ``j`` not yet done for which ``ready(j)``, on a chain of ``m`` frames (so far)."""
        st, k = self.state, self.k
        todo = []
        j = len(st.net)
        while ready(j) and j + 1 < m:
            todo.append(j)
            j += 1
        for n in range(0, len(todo), self.batch):
            chunk = todo[n : n + self.batch]
            nets = []
            for j in chunk:
                c = window_centre(j, m, k)
                nets.append(step_from_window(st.windows[c - k], c, j, k))
            self._pairs(chunk, np.stack(nets))

    def _pairs(self, chunk: list[int], nets: np.ndarray) -> None:
        st = self.state
        t = time.perf_counter()
        tgt = self._view(torch.stack([self.images[j] for j in chunk]))
        src = self._view(torch.stack([self.images[j + 1] for j in chunk]))
        net = torch.from_numpy(nets)
        comp = net.clone()
        mask = self._view(self.mask) if self.mask is not None else None
        if self.view.wraps:
            comp[:, :3, :3] = yaw_matrix(compass_yaw(tgt, src, mask), dtype=torch.float64)
        t = self.times.add("compass", t)
        st.net += list(nets)
        st.compass += list(comp.numpy())
        if self.refine:
            self._refine(chunk, comp[:, :3, :3])
            self.times.add("refinement", t)

    def _keyframe(self, j: int) -> int:
        """The keyframe that step ``j``'s source (frame ``j + 1``) is aligned to."""
        return j - j % self.every

    def _refine(self, chunk: list[int], consecutive_yaw: Tensor) -> None:
        """Align the source of each step of ``chunk`` (frame ``j+1``) to its keyframe ``K``: ``T_{K->j+1}``,
        started from the network's steps from ``K`` chained (or with the compass's yaw from ``K``;
        ``consecutive_yaw`` ``[B,3,3]``: its rotations between frames ``j`` and ``j+1``, the same pairs
        when every frame is a keyframe)."""
        st = self.state
        keys = [self._keyframe(j) for j in chunk]
        mask = self._view(self.mask) if self.mask is not None else None
        tgt = self._view(torch.stack([self.images[key] for key in keys]))
        src = self._view(torch.stack([self.images[j + 1] for j in chunk]))
        init = []
        for j, key in zip(chunk, keys, strict=True):
            rel = np.eye(4)
            for i in range(key, j + 1):
                rel = st.net[i] @ rel
            init.append(rel)
        start = self._rescaled(keys, torch.from_numpy(np.stack(init)))
        cands = start[:, None]
        if self.view.wraps:  # the compass's yaw with the network's translation
            turned = start.clone()
            same = self.every == 1
            turned[:, :3, :3] = (
                consecutive_yaw if same else yaw_matrix(compass_yaw(tgt, src, mask), dtype=torch.float64)
            )
            cands = torch.stack((start, turned), 1)
        depth = torch.stack([self.depths[key] for key in keys])
        res = align(tgt, src, depth, cands, self.view, config=self.align_config, mask=mask)
        st.refined += list(res.poses.cpu().numpy())
        st.cost += list(
            torch.stack((res.start_cost, res.cost, res.start.double(), res.valid.double()), 1).numpy()
        )

    def _rescaled(self, targets: list[int], net: Tensor) -> Tensor:
        """The network's poses from ``targets`` with their translation in the unit of the depth used: the
        same unit, unless the depth is ground truth (then scaled by the ratio of the median depths)."""
        if not self.depth.truth:
            return net
        own = self.depth.network(torch.stack([self.images[j] for j in targets]))
        out = net.clone()
        for b, j in enumerate(targets):
            gt = self.depths[j]
            ratio = gt[gt > 0].median() / own[b][own[b] > 0].median()
            out[b, :3, 3] *= float(ratio)
        return out

    def _forget(self, all_frames: bool = False) -> None:
        """Drop the frames no later step or window needs, and record the rest in the state."""
        st = self.state
        # the next step's target or keyframe / the next window's first frame
        keep_from = min(self._keyframe(len(st.net)), len(st.windows))
        if all_frames:
            keep_from = max(self.images, default=0) + 1
        for i in [i for i in self.images if i < keep_from]:
            del self.images[i], self.depths[i]
        st.tail_index = sorted(self.images)
        st.tail_images = [self.images[i].numpy() for i in st.tail_index]
        st.tail_depths = [self.depths[i].numpy() for i in st.tail_index]


def keyframe_steps(rel: np.ndarray, every: int) -> np.ndarray:
    """Consecutive steps ``T_{j->j+1}`` ``[M-1,4,4]`` from keyframe-relative poses ``rel[j] = T_{K->j+1}``
    (``K = j - j % every``): ``T_{K->j+1} inv(T_{K->j})`` within a keyframe's frames."""
    out = np.array(rel, dtype=np.float64, copy=True)
    for j in range(len(out)):
        if j % every:
            out[j] = rel[j] @ invert(rel[j - 1])
    return out


@dataclass
class Tracked:
    """What tracking a ride gave (the rest is in the state).

    Attributes:
        steps: the consecutive steps ``T_{j->j+1}`` ``[M-1,4,4]``: the refined ones (with ``refine``),
            else the pose network's.
        timings: seconds per part of the work.
    """

    steps: np.ndarray
    timings: dict[str, float]


def track(job: Job, state: State) -> Tracked:
    """The tracking stage: read the ride in chunks (from where ``state`` left it), push them through a
    :class:`Tracker`, save the state after each; then the ride's last steps.

    Raises:
        CylsfmError: a ride too short for the pose network's window, or a frame that cannot be read.
    """
    opt, dest = job.settings, job.out
    writer = None
    if opt.save_depth_maps:
        later = opt.camera_height is not None or opt.adjusts  # scaled once the metres or the points are known
        writer = depth_writer(dest / (RAW_DEPTH if later else "depth"), state.stems)
    options = TrackOptions(
        refine=opt.refine,
        align=opt.align,
        batch_size=opt.batch_size,
        keyframe_every=opt.keyframe_every,
        need_depth=opt.camera_height is not None or opt.steady_height,
        find_mount=job.find_mount,
        places=job.places,
        mount_yaw=job.mount_yaw,
    )
    tracker = Tracker(job.predictor, job.camera, state, options, job.depth, writer, job.mask)
    times = Timings()
    if not state.finished:
        _read(job, tracker, state, times)
    refined = keyframe_steps(np.stack(state.refined), opt.keyframe_every) if opt.refine else None
    steps = refined if refined is not None else np.stack(state.net)
    return Tracked(steps, {**times.parts, **tracker.times.parts})


def _read(job: Job, tracker: Tracker, state: State, times: Timings) -> None:
    """Read the ride's frames from ``state.next_frame`` on, in chunks of :data:`CHUNK` frames."""
    ride, path = job.ride, job.out / STATE_FILE
    bar = progress_bar(
        total=ride.frames or None, desc="odometry", unit="frame", enabled=job.settings.progress, leave=True
    )
    bar.update(state.next_frame)
    chunk: list[tuple[int, np.ndarray]] = []

    def flush() -> None:
        t = time.perf_counter()
        images = job.images([rgb for _, rgb in chunk])
        times.add("frames to the network's size", t)
        tracker.push([i for i, _ in chunk], images)
        state.save(path)
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
            t = times.add("decoding", t)
            if len(chunk) >= CHUNK:
                flush()
            t = time.perf_counter()
        if chunk:
            flush()
    finally:
        bar.close()
    m, need = state.next_frame, job.predictor.window_length
    if m < need:
        raise CylsfmError(f"{ride.path}: {m} frames; a trajectory needs at least {need}")
    tracker.finish(m)
    state.finished = True
    state.save(path)
