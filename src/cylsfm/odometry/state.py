"""What a run of :func:`cylsfm.odometry` has done so far, saved so that a killed run continues.

The state is one ``.npz`` file (NumPy arrays only, read with ``allow_pickle=False``) written atomically
after every chunk of frames: the network's windows and steps, the refined steps, the per-frame ground
heights, the direction of travel found, the place descriptors, the last few frames and depths that the
next steps still need, and the verified loops. It holds progress only, never a setting; it carries the
fingerprint of everything that changes that progress (input, checkpoint, options: the run's
:class:`~cylsfm.odometry.job.Job`), and a state with another fingerprint is not continued: the run starts
over.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes
from .loops.loop import Loop
from .loops.store import loops_from_arrays, loops_to_arrays

__all__ = ["STATE_FILE", "State"]

#: The state's file name in the output directory.
STATE_FILE = ".odometry-state.npz"


def _stack(rows: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    return np.stack(rows) if rows else np.zeros((0, *shape))


@dataclass
class State:
    """A run's progress. Lists grow frame by frame (``stems``, ``times``, ``heights``), window by window
    (``windows``: ``[S,4,4]`` per centre, centres ``k, k+1, ...``) and step by step (``net``, ``refined``,
    ``compass``: ``T_{j->j+1}`` ``[4,4]``; ``cost``: ``(start cost, final cost, start, valid)``)."""

    key: str
    stems: list[str] = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    heights: list[float] = field(default_factory=list)
    windows: list[np.ndarray] = field(default_factory=list)
    net: list[np.ndarray] = field(default_factory=list)
    refined: list[np.ndarray] = field(default_factory=list)
    compass: list[np.ndarray] = field(default_factory=list)
    cost: list[np.ndarray] = field(default_factory=list)
    #: the frames still needed, by index: network-size images ``[3,H,W]`` and view depths ``[1,h,w]``
    tail_index: list[int] = field(default_factory=list)
    tail_images: list[np.ndarray] = field(default_factory=list)
    tail_depths: list[np.ndarray] = field(default_factory=list)
    finished: bool = False
    #: the depth files in their final unit are all written (from the maps waiting in network units)
    rescaled: bool = False
    #: each frame's factor to the adjusted points and the points it was measured on (empty: none)
    depth_factors: np.ndarray = field(default_factory=lambda: np.zeros(0))
    depth_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    #: each frame's place descriptor (:func:`~cylsfm.geometry.place.place_descriptor`) and median depth
    places: list[np.ndarray] = field(default_factory=list)
    reach: list[float] = field(default_factory=list)
    #: the loops verified at the end, accepted or not; ``None``: not looked for yet
    loops: list[Loop] | None = None
    #: the fingerprint of the loop settings the loops were found with: other settings look again (the
    #: tracking, which they do not change, is kept)
    loop_key: str = ""
    #: the direction of travel in the panorama found from the frames (radians; nan: not found, or not
    #: looked for) and how: ``(agreement, pairs)`` of :func:`~cylsfm.odometry.mount.mount_yaw`
    mount: tuple[float, float, int] = (float("nan"), float("nan"), 0)
    #: the bundle adjustment's steps ``T_{j->j+1}`` ``[4,4]`` each, its summary's numbers and the fingerprint
    #: of the settings they were made with (``""``: not adjusted)
    bundled: list[np.ndarray] = field(default_factory=list)
    bundle_summary: dict[str, float] = field(default_factory=dict)
    bundle_key: str = ""
    #: its points ``[P,6]``: position (the odometry's unit) and colour
    bundle_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    #: their observations ``[N,4]``: frame, point, keypoint ``(u, v)`` in the frame's pixels
    bundle_tracks: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    @property
    def next_frame(self) -> int:
        return len(self.stems)

    def save(self, path: Path) -> None:
        """Write atomically to ``path``."""
        arrays = {
            "key": np.array(self.key),
            "stems": np.array(self.stems, dtype=str),
            "times": np.array(self.times, dtype=np.float64),
            "heights": np.array(self.heights, dtype=np.float64),
            "windows": _stack(self.windows, (0, 4, 4)),
            "net": _stack(self.net, (4, 4)),
            "refined": _stack(self.refined, (4, 4)),
            "compass": _stack(self.compass, (4, 4)),
            "cost": _stack(self.cost, (4,)),
            "tail_index": np.array(self.tail_index, dtype=np.int64),
            "tail_images": _stack(self.tail_images, (0, 0, 0)).astype(np.float32),
            "tail_depths": _stack(self.tail_depths, (0, 0, 0)).astype(np.float32),
            "finished": np.array(self.finished),
            "rescaled": np.array(self.rescaled),
            "depth_factors": np.asarray(self.depth_factors, dtype=np.float64),
            "depth_points": np.asarray(self.depth_points, dtype=np.int64),
            "mount": np.array(self.mount, dtype=np.float64),
            "places": _stack(self.places, (0,)).astype(np.float32),
            "reach": np.array(self.reach, dtype=np.float64),
            "loops_done": np.array(self.loops is not None),
            "loop_key": np.array(self.loop_key),
            "bundled": _stack(self.bundled, (4, 4)),
            "bundle_names": np.array(list(self.bundle_summary), dtype=str),
            "bundle_values": np.array(list(self.bundle_summary.values()), dtype=np.float64),
            "bundle_key": np.array(self.bundle_key),
            "bundle_points": np.asarray(self.bundle_points, dtype=np.float64).reshape(-1, 6),
            "bundle_tracks": np.asarray(self.bundle_tracks, dtype=np.float64).reshape(-1, 4),
            **{f"loopdata_{k}": v for k, v in loops_to_arrays(self.loops or []).items()},
        }
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: Path, key: str | None) -> State | None:
        """The saved state at ``path`` when it exists, reads, and has fingerprint ``key`` (``None``: any);
        else ``None``."""
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                if key is not None and str(z["key"]) != key:
                    return None
                state = cls(str(z["key"]))
                state.stems = [str(s) for s in z["stems"]]
                state.times = [float(t) for t in z["times"]]
                state.heights = [float(h) for h in z["heights"]]
                for name in ("windows", "net", "refined", "compass", "cost", "tail_images", "tail_depths"):
                    setattr(state, name, list(z[name]))
                state.tail_index = [int(i) for i in z["tail_index"]]
                state.finished = bool(z["finished"])
                state.rescaled = bool(z["rescaled"])
                if "depth_factors" in z.files:
                    state.depth_factors = np.asarray(z["depth_factors"], dtype=np.float64)
                    state.depth_points = np.asarray(z["depth_points"], dtype=np.int64)
                yaw, agreement, pairs = (float(v) for v in z["mount"])
                state.mount = (yaw, agreement, int(pairs))
                state.places = list(z["places"])
                state.reach = [float(r) for r in z["reach"]]
                if bool(z["loops_done"]):
                    state.loops = loops_from_arrays(
                        {k[9:]: z[k] for k in z.files if k.startswith("loopdata_")}
                    )
                state.loop_key = str(z["loop_key"])
                state.bundled = list(z["bundled"])
                state.bundle_summary = {
                    str(k): float(v) for k, v in zip(z["bundle_names"], z["bundle_values"], strict=True)
                }
                state.bundle_key = str(z["bundle_key"])
                state.bundle_points = np.asarray(z["bundle_points"], dtype=np.float64).reshape(-1, 6)
                if "bundle_tracks" in z.files:
                    state.bundle_tracks = np.asarray(z["bundle_tracks"], dtype=np.float64).reshape(-1, 4)
                else:  # a state from before the tracks were kept: adjusted again
                    state.bundle_key = ""
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None  # unreadable (empty, cut off, not an archive) or from another version: start over
        return state
