"""A ride as a COLMAP model and a nerfstudio ``transforms.json``: virtual pinhole views of every panorama,
posed by the ride's trajectory, with 3D points from the depth, for Gaussian splatting and NeRF trainers.

Each panorama is seen by ``yaws`` virtual pinhole cameras turned evenly about the vertical axis (all with
the same centre; field of view ``fov``), rendered from the panorama itself at its own resolution. In COLMAP
(4.x: images belong to frames and rigs) the ``yaws`` cameras form one rig whose reference sensor is the view
straight ahead; every panorama is a frame of that rig, posed by ``rig_from_world`` (the inverse of the
trajectory's camera-to-world pose: the camera axes are the same, x right, y down, z forward), and each of its
views an image. Points: a regular sample of each panorama's depth (``points_per_frame``), back-projected by
the panorama's own camera model into the world, coloured by the panorama, each with the track of the views
of its panorama that see it and the keypoint where it projects.

Conventions (tested against pycolmap's own reader and camera model): COLMAP stores world-to-camera poses
(quaternions w-first in its text files) and puts pixel centres at +0.5, so a keypoint is the project's pixel
coordinate + 0.5 and the principal point of a centred view is ``(W/2, H/2)``; the cameras are ``PINHOLE``.
nerfstudio's ``transforms.json`` holds camera-to-world matrices in OpenGL camera axes (x right, y up, z
back), the same world as the COLMAP model (``applied_transform``: the identity) and ``ply_file_path`` to the
same points.
"""

from __future__ import annotations

import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..atomic import atomic_write_bytes, atomic_write_text
from ..errors import CylsfmError, InputError
from ..geometry import Camera, PinholeCamera, rotation_y, sample_image

__all__ = ["ColmapWriter", "ViewOptions", "render_view", "view_rotations"]


@dataclass(frozen=True)
class ViewOptions:
    """The virtual pinhole views of each panorama and what is written.

    Attributes:
        yaws: views per panorama, turned evenly about the vertical axis (the first straight ahead).
        fov: each view's horizontal field of view in degrees (below 180).
        width, height: each view's size in pixels (``height`` ``None``: square).
        points_per_frame: 3D points sampled from each panorama's depth (at most).
        image_format: ``"jpg"`` (quality 95) or ``"png"``.
        text: also write the COLMAP model as text (``sparse/0/*.txt`` beside the binary files).
    """

    yaws: int = 4
    fov: float = 90.0
    width: int = 512
    height: int | None = None
    points_per_frame: int = 2000
    image_format: str = "jpg"
    text: bool = False

    def __post_init__(self) -> None:
        if self.yaws < 1:
            raise InputError(f"yaws must be at least 1, got {self.yaws}")
        if not 0 < self.fov < 180:
            raise InputError(f"the views' field of view must be between 0 and 180 degrees, got {self.fov}")
        if self.width < 8 or (self.height is not None and self.height < 8):
            raise InputError(f"views must be at least 8 pixels wide and high, got {self.width}x{self.height}")
        if self.points_per_frame < 0:
            raise InputError(f"points_per_frame must be at least 0, got {self.points_per_frame}")
        if self.image_format not in ("jpg", "png"):
            raise InputError(f"image_format must be jpg or png, got {self.image_format!r}")

    @property
    def camera(self) -> PinholeCamera:
        """The views' pinhole camera (the project's pixel-centre convention)."""
        return PinholeCamera.from_fov(self.width, self.height or self.width, self.fov)


def view_rotations(yaws: int) -> np.ndarray:
    """``[K,3,3]`` rotations ``pano_from_view`` of ``K`` views turned evenly about the vertical axis, the
    first straight ahead: view ``k`` looks along azimuth ``2 pi k / K`` (``atan2(x, z)``, to the right)."""
    return rotation_y(2 * math.pi * np.arange(yaws) / yaws)


def render_view(
    rgb: np.ndarray, camera: Camera, view: PinholeCamera, pano_from_view: np.ndarray
) -> np.ndarray:
    """The pinhole ``view`` (turned by ``pano_from_view`` ``[3,3]``) of the panorama ``rgb`` (``uint8
    [H,W,3]`` of ``camera``), sampled bilinearly across the seam: ``uint8 [h,w,3]`` (black where the
    panorama does not see)."""
    rays = view.rays(view.pixel_grid(1, dtype=torch.float64))  # [1,3,h,w]
    turned = torch.einsum("ij,bjhw->bihw", torch.from_numpy(pano_from_view).double(), rays)
    uv = camera.project(turned)
    image = torch.from_numpy(np.require(rgb, np.uint8, ["C", "W"])).permute(2, 0, 1)[None].double()
    sampled, valid = sample_image(image, uv, camera.wraps)
    out = torch.where(valid & camera.projectable(turned), sampled, torch.zeros(()))
    return out[0].permute(1, 2, 0).round().clamp(0, 255).byte().numpy()


@dataclass
class _Points:
    xyz: list[np.ndarray] = field(default_factory=list)
    rgb: list[np.ndarray] = field(default_factory=list)


class ColmapWriter:
    """Writes ``OUT/images/``, ``OUT/sparse/0/`` (COLMAP, binary), ``OUT/transforms.json`` and
    ``OUT/sparse_pc.ply`` from panoramas added one at a time (see the module docstring).

    Args:
        out: the output folder (created).
        options: the views and what to write.
    """

    def __init__(self, out: str | os.PathLike[str], options: ViewOptions | None = None) -> None:
        try:
            import pycolmap
        except ImportError:
            raise CylsfmError(
                "export colmap needs pycolmap: pip install 'cylsfm[colmap]' (or pycolmap>=4.0)"
            ) from None
        self.pc = pycolmap
        self.out = Path(out)
        self.options = options or ViewOptions()
        self.view = self.options.camera
        self.rotations = view_rotations(self.options.yaws)
        self.rec = pycolmap.Reconstruction()
        self.points = _Points()
        self.frames: list[dict] = []
        self._rig()

    def _rig(self) -> None:
        pc, v = self.pc, self.view
        params = [float(v.fx), float(v.fy), v.width / 2, v.height / 2]  # centred: COLMAP's centres at +0.5
        rig = pc.Rig(rig_id=1)
        for k, rot in enumerate(self.rotations):
            cam = pc.Camera(camera_id=k + 1, model="PINHOLE", width=v.width, height=v.height, params=params)
            self.rec.add_camera(cam)
            sensor = pc.sensor_t(type=pc.SensorType.CAMERA, id=k + 1)
            if k == 0:
                rig.add_ref_sensor(sensor)
            else:  # view_from_pano: the rig's frame is the panorama's (the first view's)
                rig.add_sensor(sensor, pc.Rigid3d(np.hstack([rot.T, np.zeros((3, 1))])))
        self.rec.add_rig(rig)

    def add(
        self,
        name: str,
        rgb: np.ndarray,
        camera: Camera,
        c2w: np.ndarray,
        depth: np.ndarray,
        depth_camera: Camera,
        mask: np.ndarray | None = None,
    ) -> None:
        """Add one panorama.

        Args:
            name: the frame's name (its views are ``images/NAME_KK.jpg``).
            rgb: the panorama ``uint8 [H,W,3]`` of ``camera`` (views are rendered from it).
            c2w: its camera-to-world pose ``[4,4]`` (the trajectory's unit).
            depth: its depth ``[h,w]`` in ``depth_camera`` (same centre and axes; same unit as ``c2w``;
                0 unknown); mask: ``[h,w]``, 0 where no point is taken (an occluder).
        """
        n = len(self.frames)
        frame_id, first_image = n + 1, n * self.options.yaws + 1
        world_from_pano = np.asarray(c2w, dtype=np.float64)
        xyz, colour, observations = self._sample(rgb, camera, depth, depth_camera, mask)
        pc = self.pc
        frame = pc.Frame(
            frame_id=frame_id, rig_id=1, rig_from_world=pc.Rigid3d(np.linalg.inv(world_from_pano)[:3])
        )
        for k in range(self.options.yaws):
            frame.add_data_id(
                pc.data_t(sensor_id=pc.sensor_t(type=pc.SensorType.CAMERA, id=k + 1), id=first_image + k)
            )
        self.rec.add_frame(frame)
        names = []
        for k, rot in enumerate(self.rotations):
            file = f"{name}_{k:02d}.{self.options.image_format}"
            self._write_image(file, render_view(rgb, camera, self.view, rot))
            image = pc.Image(image_id=first_image + k, name=file, camera_id=k + 1, frame_id=frame_id)
            image.points2D = pc.Point2DList([pc.Point2D(xy) for xy in observations[k][1]])
            self.rec.add_image(image)
            names.append(file)
        world = xyz @ world_from_pano[:3, :3].T + world_from_pano[:3, 3]
        tracks: list[list[tuple[int, int]]] = [[] for _ in range(len(xyz))]
        for k, (which, _) in enumerate(observations):
            for idx, p in enumerate(which):
                tracks[p].append((first_image + k, idx))
        for p, elements in enumerate(tracks):
            if elements:
                track = pc.Track()
                for image_id, idx in elements:
                    track.add_element(image_id, idx)
                self.rec.add_point3D(world[p], track, colour[p])
        seen = [bool(t) for t in tracks]
        self.points.xyz.append(world[seen])
        self.points.rgb.append(colour[seen])
        self.frames.append({"names": names, "world_from_pano": world_from_pano})

    def _sample(
        self,
        rgb: np.ndarray,
        camera: Camera,
        depth: np.ndarray,
        depth_camera: Camera,
        mask: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray, list[tuple[list[int], list[np.ndarray]]]]:
        """``(points [N,3] in the panorama's frame, colours uint8 [N,3], per view: (the points it sees,
        their keypoints in COLMAP's pixel coordinates))``."""
        h, w = depth.shape
        if (w, h) != depth_camera.size:
            raise CylsfmError(f"depth of {w}x{h} for a camera of {depth_camera.width}x{depth_camera.height}")
        keep = np.isfinite(depth) & (depth > 0)
        if mask is not None:
            keep &= mask > 0
        stride = max(1, math.ceil(math.sqrt(keep.sum() / max(self.options.points_per_frame, 1))))
        grid = np.zeros_like(keep)
        grid[stride // 2 :: stride, stride // 2 :: stride] = True
        vv, uu = np.nonzero(keep & grid)
        if self.options.points_per_frame == 0:
            vv, uu = vv[:0], uu[:0]
        d = torch.from_numpy(depth.astype(np.float64))[None, None]
        pts = depth_camera.unproject(d)[0].permute(1, 2, 0).numpy()[vv, uu]  # [N,3]
        uv = camera.project(torch.from_numpy(pts).T.reshape(1, 3, 1, -1))  # the panorama's pixel of each
        image = torch.from_numpy(np.require(rgb, np.uint8, ["C", "W"])).permute(2, 0, 1)[None].double()
        colour = sample_image(image, uv, camera.wraps)[0][0, :, 0].T.round().clamp(0, 255).byte().numpy()
        observations = []
        for rot in self.rotations:
            in_view = pts @ rot  # view_from_pano @ p, for every point (rows)
            z = in_view[:, 2]
            ok = z > 1e-9
            uvv = self.view.project(torch.from_numpy(in_view).T.reshape(1, 3, 1, -1))[0, :, 0].T.numpy()
            ok &= (uvv[:, 0] >= -0.5) & (uvv[:, 0] <= self.view.width - 0.5)
            ok &= (uvv[:, 1] >= -0.5) & (uvv[:, 1] <= self.view.height - 0.5)
            which = np.nonzero(ok)[0]
            observations.append((which.tolist(), [uvv[i] + 0.5 for i in which]))
        return pts, colour, observations

    def _write_image(self, file: str, image: np.ndarray) -> None:
        buf = io.BytesIO()
        if self.options.image_format == "jpg":
            Image.fromarray(image).save(buf, format="JPEG", quality=95)
        else:
            Image.fromarray(image).save(buf, format="PNG")
        atomic_write_bytes(self.out / "images" / file, buf.getvalue())

    def finish(self) -> dict:
        """Write the COLMAP model, ``transforms.json`` and ``sparse_pc.ply``; returns a summary."""
        if not self.frames:
            raise CylsfmError(f"{self.out}: no panorama was added")
        sparse = self.out / "sparse" / "0"
        sparse.mkdir(parents=True, exist_ok=True)
        self.rec.write(str(sparse))
        if self.options.text:
            self.rec.write_text(str(sparse))
        xyz = np.concatenate(self.points.xyz) if self.points.xyz else np.zeros((0, 3))
        rgb = np.concatenate(self.points.rgb) if self.points.rgb else np.zeros((0, 3), np.uint8)
        _write_points(self.out / "sparse_pc.ply", xyz, rgb)
        atomic_write_text(self.out / "transforms.json", json.dumps(self._transforms(), indent=1) + "\n")
        return {
            "panoramas": len(self.frames),
            "images": self.rec.num_images(),
            "points": self.rec.num_points3D(),
            "mean_track_length": float(self.rec.compute_mean_track_length())
            if self.rec.num_points3D()
            else 0.0,
        }

    def _transforms(self) -> dict:
        v = self.view
        gl = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL's
        frames = []
        for f in self.frames:
            for name, rot in zip(f["names"], self.rotations, strict=True):
                pano_from_view = np.eye(4)
                pano_from_view[:3, :3] = rot
                c2w = f["world_from_pano"] @ pano_from_view @ gl
                frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
        return {
            "camera_model": "OPENCV",
            "w": v.width,
            "h": v.height,
            "fl_x": float(v.fx),
            "fl_y": float(v.fy),
            "cx": v.width / 2,
            "cy": v.height / 2,
            "k1": 0.0,
            "k2": 0.0,
            "p1": 0.0,
            "p2": 0.0,
            "applied_transform": np.eye(4)[:3].tolist(),
            "ply_file_path": "sparse_pc.ply",
            "frames": frames,
        }


def _write_points(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    vertex = np.empty(
        len(xyz),
        dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    for i, k in enumerate("xyz"):
        vertex[k] = xyz[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        vertex[k] = rgb[:, i]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")], text=False).write(buf)
    atomic_write_bytes(path, buf.getvalue())
