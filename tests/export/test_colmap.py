"""``cylsfm export colmap``: a ride as a COLMAP model and a nerfstudio transforms.json, checked with
pycolmap's own reader and camera model, and against the conventions written out here in closed form."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cylsfm.cli import main
from cylsfm.data.format import load_depth
from cylsfm.data.io import read_tum
from cylsfm.data.synth import generate_dataset
from cylsfm.export.colmap import ViewOptions, view_rotations
from helpers import untrained_checkpoint

pycolmap = pytest.importorskip("pycolmap")

VIEW = 64  # the views' size in pixels (90 degrees: f = 32)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("colmap")
    generate_dataset(
        root / "data", sequences=1, frames=8, width=128, height=32, seed=4, workers=1, progress=False
    )
    ckpt = untrained_checkpoint(root)
    out = root / "out"
    args = ["export", "colmap", str(root / "data" / "seq_000"), str(out), "--checkpoint", str(ckpt)]
    args += [
        "--view-size",
        str(VIEW),
        "--points-per-frame",
        "300",
        "--device",
        "cpu",
        "--no-progress",
        "--text",
    ]
    assert main(args) == 0
    return root / "data" / "seq_000", out


def _pano_from_view(k: int, yaws: int = 4) -> np.ndarray:
    """Written out: view k looks along azimuth 2 pi k / yaws (atan2(x, z), to the right)."""
    a = 2 * math.pi * k / yaws
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def test_the_model_reads_back_with_every_pose_as_the_trajectory_says(exported):
    _, out = exported
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    c2w = read_tum(out / "odometry" / "trajectory.txt")[1]
    assert (
        rec.num_frames() == 8 and rec.num_images() == 32 and rec.num_rigs() == 1 and rec.num_points3D() > 500
    )
    assert len(list((out / "images").iterdir())) == 32  # flat, unique names
    for image in rec.images.values():
        frame, k = int(image.name[:6]), int(image.name[7:9])
        world_from_view = c2w[frame].copy()
        world_from_view[:3, :3] = world_from_view[:3, :3] @ _pano_from_view(k)
        expected = np.linalg.inv(world_from_view)[:3]
        np.testing.assert_allclose(image.cam_from_world().matrix(), expected, atol=1e-9)
    for camera in rec.cameras.values():  # what Gaussian-splatting trainers take: PINHOLE, centred
        assert camera.model == pycolmap.CameraModelId.PINHOLE
        assert list(camera.params) == pytest.approx([VIEW / 2, VIEW / 2, VIEW / 2, VIEW / 2])
    text = (out / "sparse" / "0" / "images.txt").read_text().splitlines()
    first = next(line for line in text if not line.startswith("#")).split()
    q = rec.images[int(first[0])].cam_from_world().rotation.quat  # pycolmap: x, y, z, w
    assert [float(x) for x in first[1:5]] == pytest.approx([q[3], q[0], q[1], q[2]])  # the file: w first


def test_every_point_projects_onto_its_keypoints(exported):
    _, out = exported
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.compute_mean_track_length() > 1.5  # seen from the neighbouring panoramas too
    worst = 0.0
    for point in rec.points3D.values():
        assert point.track.length() >= 1
        for el in point.track.elements:
            image = rec.images[el.image_id]
            xy = image.project_point(point.xyz)  # pycolmap's own camera model
            worst = max(worst, float(np.abs(xy - image.points2D[el.point2D_idx].xy).max()))
    assert worst < 1e-6


def test_a_cylinder_pixel_lands_where_the_closed_form_says(exported):
    """From a pixel of a panorama's depth map, by the conventions alone (cylinder: theta = (u - cx)/fx,
    h = (v - cy)/fy, p = d (sin theta, h, cos theta); pinhole with COLMAP's pixel centres at +0.5), to the
    keypoint the model records for that point."""
    _, out = exported
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    c2w = read_tum(out / "odometry" / "trajectory.txt")[1]
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    ids = list(rec.points3D)
    checked = across = 0
    for frame in (0, 5):
        depth = load_depth(out / "odometry" / "depth" / f"{frame:06d}.npy")
        h, w = depth.shape
        # the model's cylinder: fx = W / 2 pi, cx = W / 2; rows span h in [-1, 1] edge to edge
        fx, cx, fy, cy = w / (2 * math.pi), w / 2, h / 2, (h - 1) / 2
        for v in range(h):
            for u in range(w):
                theta, hh, d = (u - cx) / fx, (v - cy) / fy, float(depth[v, u])
                p = d * np.array([math.sin(theta), hh, math.cos(theta)])
                world = c2w[frame][:3, :3] @ p + c2w[frame][:3, 3]
                nearest = int(np.argmin(np.linalg.norm(xyz - world, axis=1)))
                if np.linalg.norm(xyz[nearest] - world) > 1e-5:
                    continue  # not a sampled pixel
                point = rec.points3D[ids[nearest]]
                for el in point.track.elements:
                    image = rec.images[el.image_id]
                    other, k = int(image.name[:6]), int(image.name[7:9])  # a view of this or another panorama
                    local = np.linalg.inv(c2w[other]) @ np.append(world, 1.0)
                    q = _pano_from_view(k).T @ local[:3]
                    expected = [VIEW / 2 * q[0] / q[2] + VIEW / 2, VIEW / 2 * q[1] / q[2] + VIEW / 2]
                    assert image.points2D[el.point2D_idx].xy == pytest.approx(expected, abs=1e-6)
                    checked += 1
                    across += other != frame
    assert checked > 50 and across > 10  # tracks reach the neighbouring panoramas' views


def test_transforms_json_inverts_to_the_same_cameras(exported):
    _, out = exported
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    tf = json.loads((out / "transforms.json").read_text())
    assert (tf["w"], tf["h"], tf["cx"], tf["cy"]) == (VIEW, VIEW, VIEW / 2, VIEW / 2)
    assert tf["fl_x"] == pytest.approx(VIEW / 2) and tf["ply_file_path"] == "sparse_pc.ply"
    by_name = {im.name: im for im in rec.images.values()}
    assert len(tf["frames"]) == 32
    for f in tf["frames"]:
        opengl_c2w = np.array(f["transform_matrix"])
        w2c = np.linalg.inv(opengl_c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenGL axes back to OpenCV's
        image = by_name[f["file_path"].removeprefix("images/")]
        np.testing.assert_allclose(w2c[:3], image.cam_from_world().matrix(), atol=1e-9)
        assert (out / f["file_path"]).is_file()
    from plyfile import PlyData

    assert len(PlyData.read(str(out / "sparse_pc.ply"))["vertex"]) == rec.num_points3D()


def test_view_rotations_look_around_to_the_right():
    rot = view_rotations(4)
    np.testing.assert_allclose(rot[1] @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # a quarter turn right: +x
    for k in range(4):
        np.testing.assert_allclose(rot[k], _pano_from_view(k), atol=1e-12)
    with pytest.raises(Exception, match="field of view"):
        ViewOptions(fov=180)


def test_a_point_hidden_in_a_neighbour_is_not_in_its_views(tmp_path):
    """Three panoramas at the same place: the middle one's depth says a wall stands at 1 m where the others
    see 5 m, so the others' points are in the views of each other but not in the middle one's."""
    from cylsfm.export.colmap import ColmapWriter
    from cylsfm.geometry import CylindricalCamera

    cam = CylindricalCamera.full(64, 16)
    rgb = np.full((16, 64, 3), 128, np.uint8)
    writer = ColmapWriter(tmp_path, ViewOptions(yaws=4, width=32, points_per_frame=64, image_format="png"))
    for name, d in (("a", 5.0), ("b", 1.0), ("c", 5.0)):
        writer.add(name, rgb, cam, np.eye(4), np.full((16, 64), d, np.float32), cam)
    writer.finish()
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    for point in rec.points3D.values():
        frames = {rec.images[el.image_id].name[0] for el in point.track.elements}
        far = np.linalg.norm(point.xyz[[0, 2]]) > 2
        assert frames == ({"a", "c"} if far else {"b"})


def _tilted(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Written out: pano_from_view of a view turned right by yaw and tilted up by pitch (y points down)."""
    a, b = math.radians(yaw_deg), math.radians(pitch_deg)
    yaw = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    up = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    return yaw @ up


def test_view_rotations_tilt_up_for_positive_pitches():
    rot = view_rotations(4, (0.0, 30.0))
    assert rot.shape == (8, 3, 3)
    np.testing.assert_allclose(rot[:4], view_rotations(4), atol=1e-12)  # the level views first
    s, c = math.sin(math.radians(30)), math.cos(math.radians(30))
    np.testing.assert_allclose(rot[4] @ [0, 0, 1], [0, -s, c], atol=1e-12)  # up is -y
    np.testing.assert_allclose(rot[5] @ [0, 0, 1], [c, -s, 0], atol=1e-12)  # then a quarter turn right
    for bad in ((), (0.0, 0.0), (95.0,), (math.nan,)):
        with pytest.raises(Exception, match="pitches"):
            ViewOptions(pitches=bad)


def test_tilted_views_of_an_equirectangular_ride(tmp_path):
    """Views tilted up and down (the first one tilted too, so the rig's axes are not the panorama's):
    poses, keypoints and the pixels of the views by the closed forms; a cylinder refuses the tilt."""
    from cylsfm.errors import CylsfmError
    from cylsfm.export.colmap import ColmapWriter
    from cylsfm.geometry import CylindricalCamera, EquirectangularCamera

    eq = EquirectangularCamera.full(128, 64)
    rgb = np.repeat((2 * np.arange(64, dtype=np.uint8))[:, None, None], 128, 1).repeat(3, 2)  # grey = 2 row
    cyl = CylindricalCamera.full(64, 16)
    view = 33  # odd: the centre pixel looks straight along the view's axis
    opts = ViewOptions(yaws=2, pitches=(30.0, -60.0), width=view, points_per_frame=64, image_format="png")
    writer = ColmapWriter(tmp_path, opts)
    rng = np.random.default_rng(0)
    poses = []
    for name in ("a", "b"):
        c2w = np.eye(4)
        c2w[:3, :3] = _tilted(rng.uniform(-180, 180), rng.uniform(-10, 10))
        c2w[:3, 3] = rng.normal(size=3)
        poses.append(c2w)
        writer.add(name, rgb, eq, c2w, np.full((16, 64), 4.0, np.float32), cyl)
    writer.finish()
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    assert rec.num_images() == 8 and rec.num_points3D() > 50
    angles = [(0, 30), (180, 30), (0, -60), (180, -60)]
    for image in rec.images.values():
        j, k = "ab".index(image.name[0]), int(image.name[2:4])
        world_from_view = poses[j].copy()
        world_from_view[:3, :3] = world_from_view[:3, :3] @ _tilted(*angles[k])
        np.testing.assert_allclose(
            image.cam_from_world().matrix(), np.linalg.inv(world_from_view)[:3], atol=1e-9
        )
        for p in image.points2D:
            if p.has_point3D():
                xy = image.project_point(rec.points3D[p.point3D_id].xyz)
                assert np.abs(xy - p.xy).max() < 1e-6
    from PIL import Image

    for k, (_, pitch) in enumerate(angles):  # the centre pixel sees elevation -pitch (rows: y_e)
        centre = np.asarray(Image.open(tmp_path / "images" / f"a_{k:02d}.png"))[view // 2, view // 2, 0]
        y_e = 64 * (math.radians(-pitch) / math.pi + 0.5) - 0.5
        assert abs(int(centre) - 2 * y_e) <= 1
    refusing = ColmapWriter(tmp_path / "cyl", opts)
    with pytest.raises(CylsfmError, match=r"tilted by 30 degrees.*equirectangular"):
        refusing.add(
            "a", np.zeros((16, 64, 3), np.uint8), cyl, np.eye(4), np.full((16, 64), 4.0, np.float32), cyl
        )


def _bilinear(rgb: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Written out: ``rgb [H,W,3]`` sampled bilinearly at pixel coordinates (centres at integers), the
    columns wrapping round the full turn, the rows inside."""
    h, w = rgb.shape[:2]
    assert v.min() >= 0 and v.max() <= h - 1
    u0, v0 = np.floor(u).astype(int), np.minimum(np.floor(v).astype(int), h - 2)
    a, b = (u - u0)[..., None], (v - v0)[..., None]
    img = rgb.astype(np.float64)
    left, right = u0 % w, (u0 + 1) % w
    top = img[v0, left] * (1 - a) + img[v0, right] * a
    bottom = img[v0 + 1, left] * (1 - a) + img[v0 + 1, right] * a
    return top * (1 - b) + bottom * b


def _cylinder_pixels(points: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Written out: where points ``[..., 3]`` (camera axes) land in a full-turn cylindrical panorama of
    ``width x height`` whose rows span ``y / r`` in [-1, 1]: ``u = W theta / 2 pi + W / 2``,
    ``v = (H / 2) y / r + (H - 1) / 2``."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    u = width * np.arctan2(x, z) / (2 * math.pi) + width / 2
    v = (height / 2) * y / np.hypot(x, z) + (height - 1) / 2
    return u, v


def test_each_view_and_each_points_colour_is_the_panorama_resampled(tmp_path):
    """The writer on its own, a panorama of noise (so that a view turned the wrong way, mirrored or
    shifted shows other pixels), posed off the origin, with its depth at another resolution: every pixel
    of view k is the panorama sampled along that pixel's ray turned right by 2 pi k / 4 (the closed
    forms above), and every point's colour the panorama's where the point projects into it."""
    from PIL import Image

    from cylsfm.export.colmap import ColmapWriter
    from cylsfm.geometry import CylindricalCamera

    rng = np.random.default_rng(5)
    width, height = 128, 32
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    depth = (2 + rng.uniform(0, 3, (16, 1)) + np.sin(np.arange(64) / 5)).astype(np.float32)  # [16,64]
    c2w = np.eye(4)
    c2w[:3, :3] = _tilted(35.0, 5.0)
    c2w[:3, 3] = [0.7, -0.2, 1.5]
    view, fov = 24, 60.0  # narrow enough to stay within the panorama's rows
    options = ViewOptions(yaws=4, fov=fov, width=view, points_per_frame=1024, image_format="png")
    writer = ColmapWriter(tmp_path, options)
    writer.add("a", rgb, CylindricalCamera.full(width, height), c2w, depth, CylindricalCamera.full(64, 16))
    writer.finish()

    f = (view / 2) / math.tan(math.radians(fov) / 2)
    cols, rows = np.meshgrid(np.arange(view), np.arange(view))
    rays = np.stack([(cols - (view - 1) / 2) / f, (rows - (view - 1) / 2) / f, np.ones_like(cols, float)], -1)
    for k in range(4):
        image = np.asarray(Image.open(tmp_path / "images" / f"a_{k:02d}.png"))
        expected = _bilinear(rgb, *_cylinder_pixels(rays @ _pano_from_view(k).T, width, height))
        error = np.abs(image.astype(np.float64) - expected)
        assert error.max() <= 1, f"view {k} is not the panorama seen {90 * k} degrees to the right"

    rec = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    assert rec.num_points3D() > 100
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    colours = np.array([p.color for p in rec.points3D.values()], np.float64)
    local = (xyz - c2w[:3, 3]) @ c2w[:3, :3]  # pano_from_world, row by row
    expected = _bilinear(rgb, *_cylinder_pixels(local, width, height))
    assert np.abs(colours - expected).max() <= 1, "the points' colours are not the panorama's where they lie"
