"""A mask fixed to the camera reaches every consumer of pixels: with it, the occluder's content changes
nothing (alignment, compass, networks, odometry, mesh); without it, the occluder pulls the alignment to
standing still. The occluder is the synthetic generator's own (``cylsfm synth --occluder``)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from cylsfm.cli import main
from cylsfm.data.fill import fill_masked
from cylsfm.data.format import SequenceWriter, load_depth, load_image, scan_dataset
from cylsfm.data.io import load_mask
from cylsfm.data.synth import generate_dataset
from cylsfm.data.synth.occluder import occluder_mask, occluder_texture
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.errors import InputError, ShapeError
from cylsfm.geometry import CylindricalCamera, column_shift, relative_pose, roll_columns
from cylsfm.model import Predictor
from cylsfm.odometry import AlignConfig, OdometrySettings, align, odometry

CAM = CylindricalCamera.full(160, 40)


def _painted(images: torch.Tensor, occ: torch.Tensor, texture: torch.Tensor) -> torch.Tensor:
    return torch.where(occ, texture, images)


def _texture(seed: int, w: int = 160, h: int = 40) -> torch.Tensor:
    return torch.from_numpy(occluder_texture(w, h, seed)).permute(2, 0, 1).float() / 255


def _room_pair():
    target = make_pose(0.0, 0.0, 0.0, yaw_deg=180.0)
    source = make_pose(0.25, 0.05, -0.35, yaw_deg=184.0)
    tgt, depth = render_room(CAM, target, supersample=2)
    src, _ = render_room(CAM, source, supersample=2)
    return tgt, src, depth, relative_pose(target[None], source[None])[0]


def _errors(pose: torch.Tensor, true: torch.Tensor) -> tuple[float, float, float]:
    """(rotation error in degrees, direction error in degrees, length ratio)."""
    r = pose[:3, :3].T @ true[:3, :3].double()
    rot = math.degrees(math.acos(float(((r.trace() - 1) / 2).clamp(-1, 1))))
    t, tt = pose[:3, 3], true[:3, 3].double()
    cos = float(torch.dot(t, tt) / (t.norm() * tt.norm()).clamp(min=1e-12))
    return rot, math.degrees(math.acos(max(-1.0, min(1.0, cos)))), float(t.norm() / tt.norm())


@pytest.mark.parametrize("kind", ["helmet", "roof"])
def test_alignment_with_the_mask_finds_the_motion_that_the_occluder_hides(kind):
    tgt, src, depth, true = _room_pair()
    occ = torch.from_numpy(occluder_mask(160, 40, kind))
    tex = _texture(7)
    t_occ, s_occ = _painted(tgt, occ, tex), _painted(src, occ, tex)
    d_occ = torch.where(occ, torch.full_like(depth, 0.4), depth)  # the occluder is near the camera
    standing = torch.eye(4, dtype=torch.float64)[None]
    cfg = AlignConfig(levels=3, iterations=10)
    mask = (~occ).float()[None, None]
    masked = align(t_occ, s_occ, d_occ, standing, CAM, config=cfg, mask=mask)
    rot, direction, length = _errors(masked.poses[0], true)
    assert rot < 0.1 and direction < 2.0 and abs(length - 1) < 0.05
    # the content under the mask changes nothing at all
    again = align(
        _painted(tgt, occ, _texture(8)),
        _painted(src, occ, _texture(9)),
        d_occ,
        standing,
        CAM,
        config=cfg,
        mask=mask,
    )
    assert torch.equal(again.poses, masked.poses) and torch.equal(again.cost, masked.cost)
    # without the mask the static occluder holds the estimate at standing still
    unmasked = align(t_occ, s_occ, d_occ, standing, CAM, config=cfg)
    assert _errors(unmasked.poses[0], true)[2] < 0.5


def test_the_compass_ignores_what_lies_under_the_mask():
    g = torch.Generator().manual_seed(0)
    a = torch.nn.functional.avg_pool2d(
        torch.nn.functional.pad(torch.rand(1, 3, 40, 160, generator=g), (1, 1, 1, 1), mode="circular"), 3, 1
    )
    b = roll_columns(a, 7)
    occ = torch.from_numpy(occluder_mask(160, 40, "roof"))
    mask = (~occ).float()[None, None]
    shifts = [
        float(column_shift(_painted(a, occ, _texture(s)), _painted(b, occ, _texture(s + 1)), mask=mask))
        for s in (1, 5)
    ]
    assert shifts[0] == shifts[1] and abs(shifts[0] - 7) < 0.02
    plain = [
        float(column_shift(_painted(a, occ, _texture(s)), _painted(b, occ, _texture(s)))) for s in (1, 5)
    ]
    assert plain[0] != plain[1]  # without the mask the occluder's texture moves the estimate
    with pytest.raises(ShapeError, match="mask"):
        column_shift(a, b, mask=mask[..., :-1])


def test_fill_keeps_the_seen_pixels_and_fills_from_the_surroundings():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 16, 40, generator=g)
    occ = torch.from_numpy(occluder_mask(40, 16, "roof"))
    mask = (~occ).float()[None, None]
    y = fill_masked(x, mask)
    assert torch.equal(y[:, :, ~occ], x[:, :, ~occ])
    assert torch.equal(fill_masked(torch.where(occ, 5.0, x), mask), y)  # the occluder's values never enter
    lo, hi = x[:, :, ~occ].amin(), x[:, :, ~occ].amax()
    assert bool((y >= lo - 1e-6).all() and (y <= hi + 1e-6).all())
    assert torch.equal(fill_masked(x, torch.ones(1, 1, 16, 40)), x)
    with pytest.raises(ShapeError, match="mask"):
        fill_masked(x, mask[..., 1:])


def test_the_networks_see_the_occluder_filled(ckpt):
    predictor = Predictor.from_checkpoint(ckpt, "cpu")
    cam = CylindricalCamera.full(128, 32)
    g = torch.Generator().manual_seed(2)
    frames = torch.rand(2, 3, 3, 32, 128, generator=g)
    occ = torch.from_numpy(occluder_mask(128, 32, "helmet"))
    mask = (~occ).float()[None, None]
    one = _painted(frames, occ, _texture(1, 128, 32))
    two = _painted(frames, occ, _texture(2, 128, 32))
    d1, d2 = predictor.depth(one[:, 0], cam, mask), predictor.depth(two[:, 0], cam, mask)
    assert torch.equal(d1, d2) and not torch.equal(d1, predictor.depth(one[:, 0], cam))
    p1 = predictor.poses(one[:, 1], one[:, [0, 2]], cam, mask=mask)
    p2 = predictor.poses(two[:, 1], two[:, [0, 2]], cam, mask=mask)
    assert torch.equal(p1, p2)


# ----------------------------------------------------------------------------- whole rides
@pytest.fixture(scope="module")
def occluded(tmp_path_factory):
    """One ride of 24 frames at 128x32 with the helmet occluder, and the same ride with another texture
    under the occluder (the scene identical)."""
    root = tmp_path_factory.mktemp("occluded")
    generate_dataset(
        root / "a",
        sequences=1,
        frames=24,
        width=128,
        height=32,
        seed=5,
        workers=1,
        progress=False,
        occluder="helmet",
    )
    seq = scan_dataset(root / "a")[0]
    occ = occluder_mask(128, 32, "helmet")
    other = occluder_texture(128, 32, seed=99)
    writer = SequenceWriter(root / "b" / seq.name, seq.camera)
    for i, path in enumerate(seq.images):
        writer.add_frame(np.where(occ[..., None], other, load_image(path)), load_depth(seq.depth_path(i)))
    writer.finish(mask=~occ)
    shutil.copy(
        seq.path / "poses.txt", root / "b" / seq.name / "poses.txt"
    )  # the same ground truth, byte for byte
    return root / "a" / seq.name, root / "b" / seq.name


def test_synth_paints_the_occluder_and_writes_its_mask(occluded):
    seq_dir, _ = occluded
    occ = occluder_mask(128, 32, "helmet")
    assert np.array_equal(load_mask(seq_dir / "mask.png") > 0, ~occ)
    image, depth = load_image(seq_dir / "images" / "000003.png"), load_depth(seq_dir / "depth" / "000003.npy")
    assert np.array_equal(image[occ], occluder_texture(128, 32)[occ])
    assert (depth[occ] == 0).all() and (depth[~occ] != 0).any()
    with pytest.raises(InputError, match="occluder"):
        generate_dataset(seq_dir.parent / "x", sequences=1, frames=3, width=16, height=8, occluder="hat")


def _trajectories(out):
    return [np.loadtxt(out / name) for name in ("trajectory.txt", "trajectory_network.txt")]


def test_odometry_with_the_mask_does_not_see_the_occluder(occluded, ckpt, tmp_path):
    a, b = occluded
    settings = OdometrySettings(refine=True, progress=False, device="cpu")
    ra = odometry(a, ckpt, tmp_path / "a", settings)
    odometry(b, ckpt, tmp_path / "b", settings)
    for x, y in zip(_trajectories(tmp_path / "a"), _trajectories(tmp_path / "b"), strict=True):
        np.testing.assert_array_equal(x, y)  # every consumer left the occluder out (the mount search too)
    summary = json.loads((tmp_path / "a" / "odometry.json").read_text())
    assert summary["mask"]["file"] == str(a / "mask.png")
    assert summary["mask"]["occluded_fraction"] == pytest.approx(
        float(occluder_mask(128, 32).mean()), abs=0.02
    )
    assert "mask:" in (tmp_path / "a" / "trajectory.txt").read_text()
    assert ra.c2w.shape == (24, 4, 4)
    # without it, the occluder's content enters the result; the saved state is not reused for other settings
    plain = OdometrySettings(refine=True, progress=False, device="cpu", mask=False)
    odometry(a, ckpt, tmp_path / "a", plain)
    odometry(b, ckpt, tmp_path / "b2", plain)
    assert json.loads((tmp_path / "a" / "odometry.json").read_text())["mask"] is None
    assert not np.array_equal(_trajectories(tmp_path / "a")[1], _trajectories(tmp_path / "b2")[1])


def test_odometry_takes_a_mask_file_of_the_frames_aspect(occluded, ckpt, tmp_path):
    a, _ = occluded
    wrong = tmp_path / "wrong.png"
    from PIL import Image

    Image.fromarray(np.full((32, 32), 255, np.uint8)).save(wrong)
    assert (
        main(
            [
                "odometry",
                str(a),
                "--checkpoint",
                str(ckpt),
                "--out",
                str(tmp_path / "o"),
                "--mask",
                str(wrong),
                "--no-progress",
                "--device",
                "cpu",
            ]
        )
        == 2
    )
    half = tmp_path / "half.png"  # the sequence's mask at half the size: the same pixels
    Image.open(a / "mask.png").resize((64, 16), Image.Resampling.NEAREST).save(half)
    args = ["odometry", str(a), "--checkpoint", str(ckpt), "--no-progress", "--device", "cpu"]
    assert main([*args, "--out", str(tmp_path / "h"), "--mask", str(half)]) == 0
    assert json.loads((tmp_path / "h" / "odometry.json").read_text())["mask"]["file"] == str(half)


def test_the_mesh_has_no_vertex_on_the_occluder(occluded, ckpt, tmp_path):
    a, _ = occluded
    frame = a / "images" / "000004.png"
    occ = occluder_mask(128, 32, "helmet")
    from cylsfm.export.mesh import build_mesh
    from cylsfm.export.scene import load_scene

    for source in ({"checkpoint": ckpt, "device": "cpu"}, {"depth": a / "depth" / "000004.npy"}):
        mesh = build_mesh(load_scene(frame, **source), max_ratio=100.0)  # the sequence's mask.png
        u, v = mesh.pixels[:, 0], mesh.pixels[:, 1]
        assert len(mesh.vertices) and not occ[v, u].any()
    plain = build_mesh(load_scene(frame, checkpoint=ckpt, device="cpu", mask=False), max_ratio=100.0)
    assert occ[plain.pixels[:, 1], plain.pixels[:, 0]].any()
    out = tmp_path / "m.ply"
    assert main(["export", "mesh", str(frame), str(out), "--checkpoint", str(ckpt), "--device", "cpu"]) == 0
    from plyfile import PlyData

    assert len(PlyData.read(str(out))["vertex"]) == int((~occ).sum())


def test_evaluation_does_not_see_the_occluder(occluded, ckpt):
    from cylsfm.evaluate.depth import evaluate_depth
    from cylsfm.evaluate.pose import evaluate_pose

    predictor = Predictor.from_checkpoint(ckpt, "cpu")
    a, b = occluded
    poses = [evaluate_pose(predictor, root.parent, split=None) for root in (a, b)]
    assert poses[0]["model"] == poses[1]["model"] and poses[0]["compass"] == poses[1]["compass"]
    depths = [evaluate_depth(predictor, root.parent, split=None, prior_split=None) for root in (a, b)]
    assert depths[0]["model"] == depths[1]["model"]


def test_training_inputs_are_filled_under_the_mask():
    from cylsfm.train.objective import Batch

    g = torch.Generator().manual_seed(3)
    occ = torch.from_numpy(occluder_mask(64, 16, "roof"))
    tgt, src = torch.rand(2, 3, 16, 64, generator=g), torch.rand(2, 2, 3, 16, 64, generator=g)
    mask = torch.stack([(~occ).float(), torch.ones(16, 64)])[:, None]  # the second sample has none
    one = Batch(_painted(tgt, occ, _texture(1, 64, 16)), _painted(src, occ, _texture(1, 64, 16)), CAM, mask)
    two = Batch(_painted(tgt, occ, _texture(2, 64, 16)), _painted(src, occ, _texture(2, 64, 16)), CAM, mask)
    (t1, s1), (t2, s2) = one.network_inputs(), two.network_inputs()
    assert torch.equal(t1[0], t2[0]) and torch.equal(s1[0], s2[0])  # sample 0: the occluder filled
    assert not torch.equal(t1[1], t2[1]) and torch.equal(t1[1], one.target[1])  # sample 1: as it is
    assert Batch(tgt, src, CAM, None).network_inputs()[0] is tgt


def test_predict_with_the_mask_does_not_see_the_occluder(occluded, ckpt, tmp_path):
    a, b = occluded
    occ = occluder_mask(128, 32, "helmet")
    for seq, out in ((a, tmp_path / "a"), (b, tmp_path / "b")):
        args = ["predict", str(seq / "images"), "--checkpoint", str(ckpt), "--out", str(out)]
        assert main([*args, "--mask", str(seq / "mask.png"), "--device", "cpu", "--no-png"]) == 0
    for name in ("000000.npy", "000007.npy"):
        da, db = np.load(tmp_path / "a" / "images" / name), np.load(tmp_path / "b" / "images" / name)
        assert np.array_equal(da, db) and (da[occ] == 0).all() and (da[~occ] > 0).all()
    wrong = tmp_path / "square.png"
    from PIL import Image

    Image.fromarray(np.full((8, 8), 255, np.uint8)).save(wrong)
    args = ["predict", str(a / "images"), "--checkpoint", str(ckpt), "--out", str(tmp_path / "c")]
    assert main([*args, "--mask", str(wrong), "--device", "cpu"]) == 2
    assert not (tmp_path / "c" / "images").exists()  # refused before anything was written
