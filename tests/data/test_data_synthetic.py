"""The street generator: ground truth that explains the images, determinism, projections, dataset output."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from cylsfm import inverse_warp
from cylsfm.data.synth import StreetScene, SynthConfig, generate_dataset, make_camera, render_frame
from cylsfm.data.synth import cars as cars_module
from cylsfm.data.synth.prisms import BOX
from cylsfm.errors import InputError
from cylsfm.geometry import relative_pose, transform_points

#: The promise of the generator (cylsfm.data.synth.cars): a moving car's centre stays more than this far
#: (metres, horizontally) from the camera in every frame.
CLEARANCE = 3.5


@pytest.fixture(scope="module")
def scene():
    return StreetScene.generate(123, SynthConfig(frames=12, moving_cars=0))


def _warp_ratios(scene, camera, tgt, src):
    """(ratio on pixels the source sees, ratio on all valid pixels) of unwarped / warped photometric error."""
    img_t, depth_t = render_frame(scene, tgt, camera)
    img_s, depth_s = render_frame(scene, src, camera)
    to_t = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float() / 255  # noqa: E731
    t_img, s_img = to_t(img_t), to_t(img_s)
    depth = torch.from_numpy(depth_t)[None, None]
    T = relative_pose(torch.from_numpy(scene.c2w[tgt]), torch.from_numpy(scene.c2w[src])).float()[None]
    warped, valid = inverse_warp(s_img, depth, T, camera)
    valid = valid & (depth > 0)  # the sky has no depth to warp with
    # occlusion is not an error of the ground truth: keep the pixels whose 3D point the source sees
    expected = camera.depth_of(transform_points(T, camera.unproject(depth)))
    seen, _ = inverse_warp(torch.from_numpy(depth_s)[None, None], depth, T, camera)
    visible = valid & ((seen - expected).abs() < 0.05 * expected)
    out = []
    for mask in (visible, valid):
        m = mask.float()
        err_warp = float(((warped - t_img).abs() * m).sum() / m.sum())
        err_none = float(((s_img - t_img).abs() * m).sum() / m.sum())
        out.append(err_none / err_warp)
    return out


@pytest.mark.parametrize(
    ("projection", "size"), [("cylindrical", (512, 128)), ("pinhole", (256, 64)), ("equirect", (512, 256))]
)
def test_ground_truth_explains_the_next_frame(scene, projection, size):
    """Warping frame t+1 into frame t with the true depth and relative pose beats no warping 5x."""
    camera = make_camera(projection, *size)
    for t in (2, 7):
        visible, valid = _warp_ratios(scene, camera, t, t + 1)
        assert visible > 5, (t, visible)
        assert valid > 3.5, (t, valid)  # occlusions included


def test_camera_moves_like_a_cyclist(scene):
    steps = np.linalg.norm(np.diff(scene.c2w[:, :3, 3], axis=0), axis=1)
    assert 0.0 <= steps.min() and steps.max() < 2.0 and 0.5 < np.median(steps) < 1.5
    heights = -scene.c2w[:, 1, 3]
    assert np.all((heights > 1.5) & (heights < 2.0))
    # gravity (world +y) stays within a few degrees of the camera's down axis
    down = scene.c2w[:, :3, 1]
    tilt = np.degrees(np.arccos(np.clip(down[:, 1], -1, 1)))
    assert tilt.max() < 8


def test_rendering_is_deterministic_and_seeded():
    cfg = SynthConfig(frames=5, moving_cars=3)
    cam = make_camera("cylindrical", 128, 32)
    a = StreetScene.generate(7, cfg)
    b = StreetScene.generate(7, cfg)
    c = StreetScene.generate(8, cfg)
    ia, da = render_frame(a, 3, cam)
    ib, db = render_frame(b, 3, cam)
    ic, _ = render_frame(c, 3, cam)
    assert np.array_equal(ia, ib) and np.array_equal(da, db)
    assert np.array_equal(a.c2w, b.c2w)
    assert not np.array_equal(ia, ic)


def test_images_have_detail_everywhere(scene):
    """Photometric matching needs gradients: ground and facades are textured, not flat colours."""
    img, depth = render_frame(scene, 4, make_camera("cylindrical", 256, 64))
    grey = img.astype(np.float64).mean(2)
    grad = np.abs(np.diff(grey, axis=1))
    ground = (depth > 0) & (np.arange(64)[:, None] > 40)
    assert grad[ground[:, 1:]].mean() > 1.0  # grey levels per pixel on the ground
    assert (depth == 0).mean() > 0.03 and (depth == 0)[-1].sum() == 0  # sky on top, none at the bottom


def _moving_car_distances(scene) -> np.ndarray:
    """Horizontal distance [F, cars] from the camera to the centre of each moving car as rendered (the last
    3 prisms a car: underbody, body and cabin, all centred on the car)."""
    n = len(scene.static)
    out = []
    for f in range(len(scene.c2w)):
        boxes = scene.prisms_at(f).a[n:].reshape(-1, 3, 4)  # [cars, 3, (x0, x1, z0, z1)]
        centres = 0.5 * (boxes[..., [0, 2]] + boxes[..., [1, 3]])  # [cars, 3, (x, z)]
        assert np.allclose(centres, centres[:, :1])
        out.append(np.linalg.norm(centres[:, 0] - scene.c2w[f, [0, 2], 3], axis=1))
    return np.array(out)


def _static_distances(scene) -> np.ndarray:
    """Horizontal distance [F, N] from the camera to the footprint of every static object."""
    p = scene.static
    box = p.kind == BOX
    out = []
    for x, z in scene.c2w[:, [0, 2], 3]:
        dx = np.maximum(np.maximum(p.a[:, 0] - x, x - p.a[:, 1]), 0)
        dz = np.maximum(np.maximum(p.a[:, 2] - z, z - p.a[:, 3]), 0)
        cyl = np.hypot(p.a[:, 0] - x, p.a[:, 1] - z) - p.a[:, 2]
        out.append(np.where(box, np.hypot(dx, dz), cyl))
    return np.array(out)


def test_moving_cars_move_and_keep_clear_of_the_camera():
    sc = StreetScene.generate(5, SynthConfig(frames=30, moving_cars=8))
    assert len(sc.movers) == 8
    p0, p1 = sc.prisms_at(0), sc.prisms_at(10)
    n = len(sc.static)
    assert len(p0) == n + 3 * 8
    assert not np.allclose(p0.a[n:], p1.a[n:])
    assert _moving_car_distances(sc).min() > CLEARANCE
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.movers[0].speed = 0.0  # cars are values


@pytest.mark.parametrize(("seed", "frames", "n_cars"), [(18, 40, 30), (24, 40, 30), (5, 60, 40)])
def test_moving_cars_keep_the_promised_clearance(seed, frames, n_cars, monkeypatch):
    """In every frame, every moving car's centre stays more than 3.5 m (horizontally) from the camera, and
    the ride keeps to its lane 1 m clear of the parked cars, lamps, trees and buildings.

    The seeds are ones whose unchecked draws do bring a car closer (the negative control below), so the
    clearance check is exercised, not just never needed.
    """
    cfg = SynthConfig(frames=frames, moving_cars=n_cars)
    scene = StreetScene.generate(seed, cfg)
    assert len(scene.movers) == n_cars  # every car found a clear lane
    assert _moving_car_distances(scene).min() > CLEARANCE
    assert _static_distances(scene).min() > 0.9
    monkeypatch.setattr(cars_module, "CLEARANCE", -np.inf)
    assert _moving_car_distances(StreetScene.generate(seed, cfg)).min() <= CLEARANCE


def test_generate_dataset_writes_format_v1(tmp_path):
    dirs = generate_dataset(
        tmp_path, sequences=2, frames=4, width=128, height=32, seed=3, workers=1, progress=False
    )
    assert [d.name for d in dirs] == ["seq_000", "seq_001"]
    for d in dirs:
        cam = json.loads((d / "camera.json").read_text())
        assert cam["model"] == "cylindrical" and cam["width"] == 128
        assert len(list((d / "images").glob("*.png"))) == 4
        assert len(list((d / "depth").glob("*.npy"))) == 4
        lines = [
            line for line in (d / "poses.txt").read_text().splitlines() if line and not line.startswith("#")
        ]
        assert len(lines) == 4
    a = (dirs[0] / "images" / "000002.png").read_bytes()
    again = generate_dataset(
        tmp_path / "again", sequences=1, frames=4, width=128, height=32, seed=3, workers=2, progress=False
    )
    assert (again[0] / "images" / "000002.png").read_bytes() == a  # the same with parallel workers


@pytest.mark.parametrize(
    ("kwargs", "word"),
    [
        ({"sequences": 0}, "sequences"),
        ({"frames": 2}, "frames"),
        ({"width": 0}, "width"),
        ({"height": 0}, "height"),
        ({"first_index": -1}, "first_index"),
        ({"projection": "fisheye"}, "projection"),
        ({"config": SynthConfig(supersample=0)}, "supersample"),
        ({"splits": True, "split_fractions": (0.5, 0.5, 0.5)}, "fractions"),
    ],
)
def test_generate_dataset_rejects_invalid_arguments(tmp_path, kwargs, word):
    args = {"sequences": 1, "frames": 3, "width": 16, "height": 8, "workers": 1, "progress": False, **kwargs}
    with pytest.raises(InputError, match=word):
        generate_dataset(tmp_path / "out", **args)
    assert not (tmp_path / "out").exists()  # nothing written


def test_generate_dataset_writes_splits_by_sequence_and_refuses_to_replace(tmp_path):
    from cylsfm.data import make_splits, read_split

    args = {"frames": 4, "width": 32, "height": 8, "seed": 2, "workers": 1, "progress": False}
    generate_dataset(tmp_path, sequences=4, splits=True, **args)
    parts = {
        p: read_split(tmp_path / "splits" / "default" / f"{p}.txt", tmp_path)
        for p in ("train", "val", "test")
    }
    seqs = {p: {s for s, _ in v} for p, v in parts.items()}
    assert [len(seqs[p]) for p in ("train", "val", "test")] == [2, 1, 1]  # whole rides, 0.8 / 0.1 / 0.1
    assert set.union(*seqs.values()) == {f"seq_{n:03d}" for n in range(4)}
    for p, entries in parts.items():  # every target with a full 3-frame snippet of its rides
        assert sorted(entries) == sorted((q, f"{t:06d}") for q in seqs[p] for t in (1, 2))
    first = {p: (tmp_path / "splits" / "default" / f"{p}.txt").read_bytes() for p in parts}
    make_splits(tmp_path, mode="sequence", seed=2)  # what the generator promises to have called
    assert first == {p: (tmp_path / "splits" / "default" / f"{p}.txt").read_bytes() for p in parts}
    # a sequence or a split that exists stops the run before anything is rendered
    with pytest.raises(InputError, match="seq_003"):
        generate_dataset(tmp_path, sequences=2, first_index=3, **args)
    with pytest.raises(InputError, match="split"):
        generate_dataset(tmp_path, sequences=1, first_index=4, splits=True, **args)
    assert not (tmp_path / "seq_004").exists()
    # with overwrite the split is written again over every sequence in the root
    generate_dataset(tmp_path, sequences=1, first_index=4, splits=True, overwrite=True, **args)
    seqs = {
        s
        for p in ("train", "val", "test")
        for s, _ in read_split(tmp_path / "splits" / "default" / f"{p}.txt", tmp_path)
    }
    assert seqs == {f"seq_{n:03d}" for n in range(5)}
