"""A ride as a rerun recording (``.rrd``): the trajectory, each frame's panorama and depth on a time line,
and the back-projected coloured points, for the rerun viewer (``rerun RIDE.rrd``).

The world is the ride's first camera's axes (x right, y down, z forward: rerun's ``RDF``). Per frame, on the
time lines ``frame`` (its index) and ``time`` (seconds): ``world/camera`` (the camera-to-world pose),
``world/camera/points`` (the depth map's pixels back-projected by the panorama's own cylindrical model, in
the camera's frame, coloured by the panorama: no pinhole model of a panorama), ``panorama`` (the frame, at
most 1024 pixels wide, JPEG) and ``depth``. ``world/trajectory`` is the whole path (static). The file is
written aside and moved into place when complete.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..errors import CylsfmError
from ..geometry import Camera

__all__ = ["RerunWriter"]

#: The panoramas' largest width in the recording.
MAX_WIDTH = 1024


class RerunWriter:
    """Writes ``path`` (a ``.rrd`` file) from frames added one at a time (see the module docstring).

    Args:
        path: the recording to write.
        points_per_frame: points back-projected from each depth map (at most).
        unit: the unit of the poses and depths (``"metres"`` or ``"network units"``), recorded with them.
    """

    def __init__(
        self, path: str | os.PathLike[str], points_per_frame: int = 4000, unit: str = "metres"
    ) -> None:
        try:
            import rerun as rr
        except ImportError:
            raise CylsfmError("export rerun needs rerun-sdk: pip install 'cylsfm[rerun]'") from None
        self.rr = rr
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.tmp")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.points_per_frame = points_per_frame
        self.rec = rr.RecordingStream("cylsfm", recording_id=self.path.stem)
        self.rec.save(str(self.tmp))
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.rec.log("description", rr.TextDocument(f"cylsfm ride, poses and depth in {unit}"), static=True)
        self.positions: list[np.ndarray] = []

    def add(
        self,
        index: int,
        time: float,
        rgb: np.ndarray,
        c2w: np.ndarray,
        depth: np.ndarray,
        depth_camera: Camera,
        depth_rgb: np.ndarray,
        mask: np.ndarray | None = None,
    ) -> None:
        """Add frame ``index`` at ``time`` seconds: its panorama ``rgb`` (``uint8 [H,W,3]``, any size), its
        camera-to-world pose ``c2w`` ``[4,4]``, its ``depth`` ``[h,w]`` in ``depth_camera`` (0: unknown) with
        the colours of the same pixels ``depth_rgb`` (``uint8 [h,w,3]``); ``mask`` ``[h,w]``: 0 where no point
        is taken (an occluder)."""
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=index)
        rec.set_time("time", duration=float(time))
        c2w = np.asarray(c2w, dtype=np.float64)
        rec.log("world/camera", rr.Transform3D(translation=c2w[:3, 3], mat3x3=c2w[:3, :3]))
        self.positions.append(c2w[:3, 3].copy())
        keep = np.isfinite(depth) & (depth > 0)
        if mask is not None:
            keep &= mask > 0
        stride = max(1, int(np.ceil(np.sqrt(keep.sum() / max(self.points_per_frame, 1)))))
        grid = np.zeros_like(keep)
        grid[stride // 2 :: stride, stride // 2 :: stride] = True
        vv, uu = np.nonzero(keep & grid)
        points = depth_camera.unproject(torch.from_numpy(depth.astype(np.float64))[None, None])[0]
        points = points.permute(1, 2, 0).numpy()[vv, uu]
        rec.log("world/camera/points", rr.Points3D(points.astype(np.float32), colors=depth_rgb[vv, uu]))
        h, w = rgb.shape[:2]
        if w > MAX_WIDTH:
            rgb = np.asarray(
                Image.fromarray(rgb).resize((MAX_WIDTH, max(1, round(h * MAX_WIDTH / w))), Image.BOX)
            )
        rec.log("panorama", rr.Image(rgb).compress(jpeg_quality=90))
        rec.log("depth", rr.DepthImage(depth.astype(np.float32), meter=1.0))

    def add_points(self, xyz: np.ndarray, rgb: np.ndarray) -> None:
        """Log the ride's sparse points ``xyz [P,3]`` (world, the poses' unit) with colours ``rgb uint8
        [P,3]`` as ``world/points``, for the whole recording."""
        points = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
        self.rec.log("world/points", self.rr.Points3D(points, colors=np.asarray(rgb, np.uint8)), static=True)

    def finish(self) -> Path:
        """Log the whole trajectory, close the recording and move it into place."""
        if not self.positions:
            self.abort()
            raise CylsfmError(f"{self.path}: no frame was added")
        self.rec.log("world/trajectory", self.rr.LineStrips3D([np.stack(self.positions)]), static=True)
        self.rec.flush()
        self.rec.disconnect()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Close the recording and remove what was written."""
        self.rec.disconnect()
        self.tmp.unlink(missing_ok=True)
