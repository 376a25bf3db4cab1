"""A ride as a COLMAP model and a nerfstudio ``transforms.json``: virtual pinhole views of every panorama,
posed by the ride's trajectory, with 3D points from the depth, for Gaussian splatting and NeRF trainers.

Each panorama is seen by ``yaws`` virtual pinhole cameras turned evenly about the vertical axis (all with
the same centre; field of view ``fov``), at each of the ``pitches`` (tilted up or down: an equirectangular
input sees the whole sphere, so its views may look at the sky and the ground), rendered from the panorama
itself at its own resolution. In COLMAP (4.x: images belong to frames and rigs) the views form one rig whose
reference sensor is the first view (the first pitch, straight ahead); every panorama is a frame of that rig,
posed by ``rig_from_world`` (from the trajectory's camera-to-world pose: the camera axes are the same, x
right, y down, z forward), and each of its views an image. Points: a regular sample of each panorama's
depth (``points_per_frame``), back-projected by the panorama's own camera model into the world,
coloured by the panorama, each with the track of the views that see it (of its panorama and of its
neighbours along the ride, where their depth agrees) and the keypoint where it projects; or, given
(:meth:`ColmapWriter.use_points`: a bundle adjustment's), triangulated points with the keypoints that
actually saw them, each in the view that sees it nearest its centre.

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..atomic import atomic_write_bytes, atomic_write_text
from ..errors import CylsfmError, InputError
from ..geometry import Camera, PinholeCamera, rotation_x, rotation_y, sample_image
from .mesh import Mesh, write_ply

__all__ = ["ColmapWriter", "ViewOptions", "render_view", "view_rotations"]


@dataclass(frozen=True)
class ViewOptions:
    """The virtual pinhole views of each panorama and what is written.

    Attributes:
        yaws: views per pitch, turned evenly about the vertical axis (the first straight ahead).
        pitches: the views' tilts in degrees (positive: up), each with ``yaws`` views; ``(0,)``: level
            views only. Views tilted beyond what the panorama sees are refused (:meth:`ColmapWriter.add`).
        fov: each view's horizontal field of view in degrees (below 180).
        width, height: each view's size in pixels (``height`` ``None``: square).
        points_per_frame: 3D points sampled from each panorama's depth (at most).
        image_format: ``"jpg"`` (quality 95) or ``"png"``.
        text: also write the COLMAP model as text (``sparse/0/*.txt`` beside the binary files).
        track_span: a point is looked for in the views of this many panoramas before and after its own.
        track_tolerance: ... seen there when that panorama's depth agrees with its distance to this fraction.
    """

    yaws: int = 4
    pitches: tuple[float, ...] = (0.0,)
    fov: float = 90.0
    width: int = 512
    height: int | None = None
    points_per_frame: int = 2000
    image_format: str = "jpg"
    text: bool = False
    track_span: int = 2
    track_tolerance: float = 0.05

    def __post_init__(self) -> None:
        if self.yaws < 1:
            raise InputError(f"yaws must be at least 1, got {self.yaws}")
        if not self.pitches or not all(math.isfinite(p) and -90 <= p <= 90 for p in self.pitches):
            raise InputError(f"pitches must be degrees within [-90, 90], got {list(self.pitches)}")
        if len(set(self.pitches)) != len(self.pitches):
            raise InputError(f"pitches must differ from each other, got {list(self.pitches)}")
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


def view_rotations(yaws: int, pitches: tuple[float, ...] = (0.0,)) -> np.ndarray:
    """``[P*K,3,3]`` rotations ``pano_from_view`` of ``K = yaws`` views turned evenly about the vertical
    axis at each of the ``P`` pitches (degrees, positive up), pitch by pitch: view ``p*K + k`` looks along
    azimuth ``2 pi k / K`` (``atan2(x, z)``, to the right), tilted up by ``pitches[p]``
    (``rotation_y(azimuth) @ rotation_x(pitch)``: the views' horizon stays level)."""
    yaw = rotation_y(2 * math.pi * np.arange(yaws) / yaws)  # [K,3,3]
    tilt = rotation_x(np.radians(np.asarray(pitches, dtype=np.float64)))  # [P,3,3]
    return np.einsum("kij,pjl->pkil", yaw, tilt).reshape(-1, 3, 3)


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
class _Panorama:
    """What :class:`ColmapWriter` keeps of each panorama until :meth:`ColmapWriter.finish`."""

    names: list[str]  # its views' files
    world_from_pano: np.ndarray  # [4,4]
    depth: np.ndarray  # [h,w] of ``depth_camera`` (0: unknown)
    depth_camera: Camera
    points: np.ndarray  # [N,3] sampled from the depth, in the panorama's frame
    colours: np.ndarray  # uint8 [N,3]


class ColmapWriter:
    """Writes ``OUT/images/``, ``OUT/sparse/0/`` (COLMAP, binary), ``OUT/transforms.json`` and
    ``OUT/sparse_pc.ply`` from panoramas added one at a time (see the module docstring).

    A point's track holds every view, of its own panorama and of the ``options.track_span`` panoramas before
    and after it, that sees it: it lies in the view and in front of it, and the depth of that panorama where
    it lands agrees with its distance within ``options.track_tolerance`` (so a point hidden there is not
    counted).

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
        self.rotations = view_rotations(self.options.yaws, self.options.pitches)
        self.panoramas: list[_Panorama] = []
        self._covered: set[tuple] = set()  # the source cameras checked to see every view
        self._sparse: tuple[np.ndarray, ...] | None = None  # set by use_points
        self.points_from = "depth"  # or "bundle adjustment": what finish wrote

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
        """Add one panorama (its views are written now, the model at :meth:`finish`).

        Args:
            name: the frame's name (its views are ``images/NAME_KK.jpg``).
            rgb: the panorama ``uint8 [H,W,3]`` of ``camera`` (views are rendered from it).
            c2w: its camera-to-world pose ``[4,4]`` (the trajectory's unit).
            depth: its depth ``[h,w]`` in ``depth_camera`` (same centre and axes; same unit as ``c2w``;
                0 unknown); mask: ``[h,w]``, 0 where no point is taken (an occluder).
        """
        h, w = depth.shape
        if (w, h) != depth_camera.size:
            raise CylsfmError(f"depth of {w}x{h} for a camera of {depth_camera.width}x{depth_camera.height}")
        self._check_coverage(camera)
        names = []
        for k, rot in enumerate(self.rotations):
            names.append(f"{name}_{k:02d}.{self.options.image_format}")
            self._write_image(names[-1], render_view(rgb, camera, self.view, rot))
        points, colours = self._sample(rgb, camera, depth, depth_camera, mask)
        pose = np.asarray(c2w, dtype=np.float64)
        self.panoramas.append(_Panorama(names, pose, depth.astype(np.float32), depth_camera, points, colours))

    def use_points(
        self, xyz: np.ndarray, rgb: np.ndarray, panorama: np.ndarray, point: np.ndarray, bearing: np.ndarray
    ) -> None:
        """Write these points and their tracks instead of points made from the depth: ``xyz [P,3]`` (world,
        the poses' unit), colours ``rgb uint8 [P,3]``, and each observation: the panorama that saw it
        (``panorama [N]``, in the order they are added), the point (``point [N]``) and its bearing in the
        panorama's axes (``bearing [N,3]``). Each observation becomes a keypoint of the view that sees it
        nearest its centre; one that no view sees is left out, and a point left with fewer than two. When
        no point is left (a ride with too little texture), the points are made from the depth after all:
        splat trainers need points to start from."""
        self._sparse = tuple(np.asarray(a) for a in (xyz, rgb, panorama, point, bearing))

    def _check_coverage(self, camera: Camera) -> None:
        """Refuse tilted views that reach beyond what ``camera`` sees (black in the images)."""
        key = (camera.model, camera.size, float(camera.fy), float(camera.cy))
        if key in self._covered or all(p == 0 for p in self.options.pitches):
            return
        rays = self.view.rays(self.view.pixel_grid(1, dtype=torch.float64))  # [1,3,h,w]
        for rot, pitch in zip(
            self.rotations, np.repeat(self.options.pitches, self.options.yaws), strict=True
        ):
            if pitch == 0:
                continue
            turned = torch.einsum("ij,bjhw->bihw", torch.from_numpy(rot), rays)
            v = camera.project(turned)[:, 1]
            inside = camera.projectable(turned)[:, 0] & (v >= -0.5) & (v <= camera.height - 0.5)
            if float(inside.double().mean()) < 0.999:
                raise CylsfmError(
                    f"views tilted by {pitch:g} degrees reach beyond what the {camera.width}x{camera.height} "
                    f"{camera.model} frames see (they would be black there): tilted views need an "
                    "equirectangular input, or smaller --pitches or --fov"
                )
        self._covered.add(key)

    def _sample(
        self,
        rgb: np.ndarray,
        camera: Camera,
        depth: np.ndarray,
        depth_camera: Camera,
        mask: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(points [N,3] in the panorama's frame, colours uint8 [N,3])``: a regular sample of the known
        depth (at most ``points_per_frame``), coloured by the panorama where each point lies."""
        keep = np.isfinite(depth) & (depth > 0)
        if mask is not None:
            keep &= mask > 0
        n = self.options.points_per_frame
        stride = max(1, math.ceil(math.sqrt(keep.sum() / max(n, 1))))
        grid = np.zeros_like(keep)
        grid[stride // 2 :: stride, stride // 2 :: stride] = n > 0
        vv, uu = np.nonzero(keep & grid)
        d = torch.from_numpy(depth.astype(np.float64))[None, None]
        pts = depth_camera.unproject(d)[0].permute(1, 2, 0).numpy()[vv, uu]  # [N,3]
        uv = camera.project(torch.from_numpy(pts).T.reshape(1, 3, 1, -1))
        image = torch.from_numpy(np.require(rgb, np.uint8, ["C", "W"])).permute(2, 0, 1)[None].double()
        colour = sample_image(image, uv, camera.wraps)[0][0, :, 0].T.round().clamp(0, 255).byte().numpy()
        return pts, colour

    def _seen(self, world: np.ndarray, pano: _Panorama) -> list[tuple[np.ndarray, np.ndarray]]:
        """For each view of ``pano``: which of the points ``world`` ``[N,3]`` it sees, and their keypoints
        (COLMAP's pixel coordinates) ``[n,2]``."""
        inv = np.linalg.inv(pano.world_from_pano)
        local = world @ inv[:3, :3].T + inv[:3, 3]
        cam = pano.depth_camera
        pts = torch.from_numpy(local).T.reshape(1, 3, 1, -1)
        uv = cam.project(pts)
        there, inside = sample_image(
            torch.from_numpy(pano.depth.astype(np.float64))[None, None], uv.round(), cam.wraps
        )
        distance = cam.depth_of(pts)[0, 0, 0].numpy()
        there, inside = there[0, 0, 0].numpy(), inside[0, 0, 0].numpy()
        agree = inside & (there > 0) & (np.abs(distance - there) <= self.options.track_tolerance * there)
        out = []
        for rot in self.rotations:
            in_view = local @ rot  # view_from_pano @ p, for every point (rows)
            ok = agree & (in_view[:, 2] > 1e-9)
            uvv = self.view.project(torch.from_numpy(in_view).T.reshape(1, 3, 1, -1))[0, :, 0].T.numpy()
            ok &= (uvv[:, 0] >= -0.5) & (uvv[:, 0] <= self.view.width - 0.5)
            ok &= (uvv[:, 1] >= -0.5) & (uvv[:, 1] <= self.view.height - 0.5)
            which = np.nonzero(ok)[0]
            out.append((which, uvv[which] + 0.5))
        return out

    def _write_image(self, file: str, image: np.ndarray) -> None:
        buf = io.BytesIO()
        if self.options.image_format == "jpg":
            Image.fromarray(image).save(buf, format="JPEG", quality=95)
        else:
            Image.fromarray(image).save(buf, format="PNG")
        atomic_write_bytes(self.out / "images" / file, buf.getvalue())

    def finish(self) -> dict:
        """Write the COLMAP model, ``transforms.json`` and ``sparse_pc.ply``; returns a summary."""
        if not self.panoramas:
            raise CylsfmError(f"{self.out}: no panorama was added")
        rec = self._reconstruction()
        rec.update_point_3d_errors()  # each point's reprojection error, kept in the model
        sparse = self.out / "sparse" / "0"
        sparse.mkdir(parents=True, exist_ok=True)
        rec.write(str(sparse))
        if self.options.text:
            rec.write_text(str(sparse))
        ids = list(rec.points3D)
        xyz = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
        rgb = np.array([rec.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
        cloud = Mesh(xyz.astype(np.float32), rgb, np.zeros((0, 3), np.int32), np.zeros((0, 2), np.int64))
        write_ply(
            cloud, self.out / "sparse_pc.ply", ["cylsfm export colmap: the model's points"], points=True
        )
        atomic_write_text(self.out / "transforms.json", json.dumps(self._transforms(), indent=1) + "\n")
        n = rec.num_points3D()
        return {
            "panoramas": len(self.panoramas),
            "images": rec.num_images(),
            "points": n,
            "mean_track_length": float(rec.compute_mean_track_length()) if n else 0.0,
            "mean_reprojection_error": float(rec.compute_mean_reprojection_error()) if n else 0.0,
            "points_from": self.points_from,
        }

    def _reconstruction(self):
        """The COLMAP model: the rig of views, a frame a panorama, its images and the points with tracks."""
        pc, yaws = self.pc, len(self.rotations)
        rec = pc.Reconstruction()
        self._add_rig(rec)
        self.points_from = "depth"
        if self._sparse is not None:
            keypoints_of, (worlds, colours, tracks) = self._observed()
            if any(len(t) >= 2 for t in tracks[0]):
                self.points_from = "bundle adjustment"
        if self.points_from == "depth":  # none given, or none that two views see: the depth's
            keypoints_of, (worlds, colours, tracks) = self._from_depth()
        for j, pano in enumerate(self.panoramas):
            keypoints = keypoints_of[j]
            world_from_rig = pano.world_from_pano.copy()  # the rig's axes: the first view's
            world_from_rig[:3, :3] = world_from_rig[:3, :3] @ self.rotations[0]
            frame = pc.Frame(
                frame_id=j + 1, rig_id=1, rig_from_world=pc.Rigid3d(np.linalg.inv(world_from_rig)[:3])
            )
            for k in range(yaws):
                sensor = pc.sensor_t(type=pc.SensorType.CAMERA, id=k + 1)
                frame.add_data_id(pc.data_t(sensor_id=sensor, id=j * yaws + k + 1))
            rec.add_frame(frame)
            for k in range(yaws):
                image = pc.Image(
                    image_id=j * yaws + k + 1, name=pano.names[k], camera_id=k + 1, frame_id=j + 1
                )
                image.points2D = pc.Point2DList([pc.Point2D(xy) for xy in keypoints[k]])
                rec.add_image(image)
        for world, colour, per_point in zip(worlds, colours, tracks, strict=True):
            for p, elements in enumerate(per_point):
                if len(elements) >= (2 if self.points_from == "bundle adjustment" else 1):
                    rec.add_point3D(world[p], self._track(elements), colour[p])
        return rec

    def _from_depth(self):
        """Points sampled from each panorama's depth: per panorama its views' keypoints, and per panorama
        its points (world), colours and tracks ``[(image_id, keypoint index), ...]``."""
        yaws, span = len(self.rotations), self.options.track_span
        worlds = [p.points @ p.world_from_pano[:3, :3].T + p.world_from_pano[:3, 3] for p in self.panoramas]
        tracks = [[[] for _ in range(len(w))] for w in worlds]
        keypoints_of = []
        for j, pano in enumerate(self.panoramas):
            keypoints: list[list[np.ndarray]] = [[] for _ in range(yaws)]
            for i in range(max(0, j - span), min(len(self.panoramas), j + span + 1)):
                for k, (which, xy) in enumerate(self._seen(worlds[i], pano)):
                    for p, point in zip(which, xy, strict=True):
                        tracks[i][p].append((j * yaws + k + 1, len(keypoints[k])))
                        keypoints[k].append(point)
            keypoints_of.append(keypoints)
        return keypoints_of, (worlds, [p.colours for p in self.panoramas], tracks)

    def _observed(self):
        """The points of :meth:`use_points`, as :meth:`_from_depth` gives them."""
        xyz, rgb, panorama, point, bearing = self._sparse
        yaws = len(self.rotations)
        if len(panorama) and (panorama.min() < 0 or panorama.max() >= len(self.panoramas)):
            raise CylsfmError(f"points seen by panoramas beyond the {len(self.panoramas)} added")
        in_views = np.einsum("ni,kij->knj", bearing, self.rotations)  # [K,N,3]: view_from_pano @ b
        forward = in_views[..., 2]
        best = np.argmax(forward, axis=0)  # the view it is nearest the centre of
        local = in_views[best, np.arange(len(bearing))]
        uv = self.view.project(torch.from_numpy(local).T.reshape(1, 3, 1, -1))[0, :, 0].T.numpy()
        inside = (local[:, 2] > 1e-9) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= self.view.width - 0.5)
        inside &= (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.view.height - 0.5)
        keypoints_of = [[[] for _ in range(yaws)] for _ in self.panoramas]
        tracks: list[list] = [[] for _ in range(len(xyz))]
        for n in np.nonzero(inside)[0]:
            j, k = int(panorama[n]), int(best[n])
            tracks[int(point[n])].append((j * yaws + k + 1, len(keypoints_of[j][k])))
            keypoints_of[j][k].append(uv[n] + 0.5)  # COLMAP's pixel centres at +0.5
        return keypoints_of, ([xyz], [rgb], [tracks])

    def _add_rig(self, rec) -> None:
        """One PINHOLE camera per view direction (centred: COLMAP's pixel centres at +0.5) and their rig."""
        pc, v = self.pc, self.view
        params = [float(v.fx), float(v.fy), v.width / 2, v.height / 2]
        rig = pc.Rig(rig_id=1)
        for k, rot in enumerate(self.rotations):
            rec.add_camera(
                pc.Camera(camera_id=k + 1, model="PINHOLE", width=v.width, height=v.height, params=params)
            )
            sensor = pc.sensor_t(type=pc.SensorType.CAMERA, id=k + 1)
            if k == 0:
                rig.add_ref_sensor(sensor)
            else:  # view_from_rig = view_from_pano @ pano_from_rig (the rig's axes: the first view's)
                rig.add_sensor(sensor, pc.Rigid3d(np.hstack([rot.T @ self.rotations[0], np.zeros((3, 1))])))
        rec.add_rig(rig)

    def _track(self, elements: list[tuple[int, int]]):
        track = self.pc.Track()
        for image_id, idx in elements:
            track.add_element(image_id, idx)
        return track

    def _transforms(self) -> dict:
        v = self.view
        gl = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL's
        frames = []
        for pano in self.panoramas:
            for name, rot in zip(pano.names, self.rotations, strict=True):
                pano_from_view = np.eye(4)
                pano_from_view[:3, :3] = rot
                c2w = pano.world_from_pano @ pano_from_view @ gl
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
