"""Depth evaluation: Eigen et al. measures, median scaling, baselines, prediction directories, the CLI."""

from __future__ import annotations

import json
import math
import re
import shutil

import numpy as np
import pytest
import torch

from cylsfm.cli import main
from cylsfm.data import DatasetError, SequenceWriter, make_splits, scan_dataset
from cylsfm.errors import InputError
from cylsfm.evaluate.depth import (
    DEPTH_METRICS,
    DepthAccumulator,
    RowPrior,
    depth_errors,
    evaluate_depth,
    evaluate_depth_maps,
    resize_depth,
)
from cylsfm.geometry import CylindricalCamera


# --------------------------------------------------------------------------------------- measures
def test_depth_errors_by_hand():
    gt = np.array([1.0, 2.0, 4.0, 3.0])
    pred = np.array([2.0, 2.0, 2.0, 2.0])
    e = depth_errors(gt, pred)
    assert set(e) == set(DEPTH_METRICS)
    # |gt - pred| / gt = 1, 0, 1/2, 1/3
    assert e["abs_rel"] == pytest.approx((1 + 0 + 0.5 + 1 / 3) / 4)
    # (gt - pred)^2 / gt = 1, 0, 1, 1/3
    assert e["sq_rel"] == pytest.approx((1 + 0 + 1 + 1 / 3) / 4)
    assert e["rmse"] == pytest.approx(math.sqrt((1 + 0 + 4 + 1) / 4))
    ln2, ln15 = math.log(2), math.log(1.5)
    assert e["rmse_log"] == pytest.approx(math.sqrt((ln2**2 + 0 + ln2**2 + ln15**2) / 4))
    # max ratios 2, 1, 2, 1.5: below 1.25 one, below 1.5625 two, below 1.953 two
    assert (e["a1"], e["a2"], e["a3"]) == (0.25, 0.5, 0.5)


def test_depth_errors_accepts_tensors_and_rejects_bad_input():
    e = depth_errors(torch.tensor([1.0, 2.0]), torch.tensor([1.0, 2.0]))
    assert e["abs_rel"] == 0 and e["a1"] == 1
    with pytest.raises(InputError):
        depth_errors(np.array([1.0, 0.0]), np.array([1.0, 1.0]))
    with pytest.raises(InputError):
        depth_errors(np.array([1.0]), np.array([1.0, 1.0]))
    with pytest.raises(InputError):
        depth_errors(np.array([]), np.array([]))


def _random_pair(seed: int, h: int = 12, w: int = 20) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    gt = rng.uniform(2, 60, (h, w))
    gt[rng.random((h, w)) < 0.2] = 0  # unknown
    gt[0, 0] = 120.0  # beyond max_depth: ignored
    pred = gt * rng.uniform(0.7, 1.4, (h, w)) + 0.5
    return gt, pred


def test_median_scaling_invariance():
    pairs = [_random_pair(s) for s in range(3)]
    a = evaluate_depth_maps(pairs)
    b = evaluate_depth_maps([(g, 7 * p) for g, p in pairs])
    for k in DEPTH_METRICS:
        assert b[k] == pytest.approx(a[k], rel=1e-9)
    assert b["scale_mean"] == pytest.approx(a["scale_mean"] / 7)
    assert a["n_images"] == 3
    # without median scaling a scaled prediction is worse
    c = evaluate_depth_maps([(g, 7 * p) for g, p in pairs], median_scaling=False)
    assert c["abs_rel"] > 2 * a["abs_rel"] and c["scale_mean"] == 1 and c["scale_std"] == 0


def test_perfect_prediction_and_unknown_pixels():
    gt, _ = _random_pair(4)
    pred = gt.copy()
    pred[gt == 0] = 1000.0  # unknown ground truth: whatever is predicted there does not count
    r = evaluate_depth_maps([(gt, pred), (torch.from_numpy(gt)[None], torch.from_numpy(pred)[None, None])])
    assert r["abs_rel"] == pytest.approx(0, abs=1e-12) and r["rmse"] == pytest.approx(0, abs=1e-9)
    assert r["a1"] == 1 and r["a3"] == 1
    assert r["scale_mean"] == pytest.approx(1) and r["scale_std"] == pytest.approx(0, abs=1e-12)
    assert r["n_images"] == 2


def test_clamping_and_empty_images():
    gt = np.full((4, 4), 10.0)
    pred = np.full((4, 4), 10.0)
    pred[0] = 1e9  # clamped to max_depth = 80 after (unit) scaling
    r = evaluate_depth_maps([(gt, pred), (np.zeros((4, 4)), pred)])
    assert r["n_images"] == 1  # the all-unknown image is skipped
    assert r["rmse"] == pytest.approx(math.sqrt(70**2 * 4 / 16))


def _bilinear_coordinate(n_out: int, n_in: int) -> np.ndarray:
    """Source coordinates of the output pixel centres of a resize from ``n_in`` to ``n_out`` samples
    (``align_corners=False``): ``x = (x' + 0.5) n_in / n_out - 0.5``."""
    return (np.arange(n_out) + 0.5) * n_in / n_out - 0.5


def test_prediction_resized_to_ground_truth():
    """A ramp at half size, resized bilinearly at pixel centres: exact inside, clamped at the borders,
    blended across the seam with ``wrap``; the evaluation scores the resized map."""
    gt = np.tile(np.arange(1.0, 9.0)[:, None], (1, 16)) + np.linspace(0, 3, 16)  # grows down and along
    v, u = np.mgrid[0:4, 0:8].astype(np.float64)
    small = 2.0 + v + 0.5 * u  # [4,8]: a ramp along both axes, so a wrong resize changes the values
    rows = np.clip(_bilinear_coordinate(8, 4), 0, 3)
    cols = np.clip(_bilinear_coordinate(16, 8), 0, 7)
    want = 2.0 + rows[:, None] + 0.5 * cols[None, :]  # bilinear is exact on a ramp, clamped at the edges
    assert np.allclose(resize_depth(small, gt.shape), want, atol=1e-12)
    # across the seam: the outer columns blend with the opposite edge (column -0.25 = 3/4 col 0 + 1/4 col 7)
    x = _bilinear_coordinate(16, 8)
    lo = np.floor(x).astype(int)
    frac = x - lo
    ramp = 0.5 * np.arange(8.0)
    wrapped = 2.0 + rows[:, None] + ((1 - frac) * ramp[lo % 8] + frac * ramp[(lo + 1) % 8])[None, :]
    assert np.allclose(resize_depth(small, gt.shape, wrap=True), wrapped, atol=1e-12)
    assert not np.allclose(wrapped, want)
    r = evaluate_depth_maps([(gt, small)])
    exact = evaluate_depth_maps([(gt, want)])
    for k in DEPTH_METRICS:
        assert r[k] == pytest.approx(exact[k], rel=1e-12)
    assert r["abs_rel"] != pytest.approx(evaluate_depth_maps([(gt, np.ones_like(gt))])["abs_rel"])


def test_row_prior_histogram_median_and_resampling():
    rng = np.random.default_rng(0)
    maps = [rng.uniform(1, 50, (6, 10)) for _ in range(5)]
    maps[0][2] = 0  # unknown pixels are left out
    prior = RowPrior()
    for m in maps:
        prior.add(m)
    stack = np.concatenate([m for m in maps], 1)
    exact = np.array([np.median(row[row > 0]) for row in stack])
    assert np.allclose(prior.medians(), exact, rtol=2e-3)
    # resampled to twice the height: pixel centres, v' = (v + 0.5) / 2 - 0.5
    big = prior.depth_map(12, 3)
    assert big.shape == (12, 3) and np.all(big == big[:, :1])
    src = np.clip((np.arange(12) + 0.5) / 2 - 0.5, 0, 5)
    assert np.allclose(big[:, 0], np.interp(src, np.arange(6), prior.medians()))
    # rows without data take the nearest rows' values
    holes = RowPrior()
    m = np.ones((3, 4)) * np.array([[2.0], [0.0], [8.0]])
    holes.add(m)
    assert np.allclose(holes.medians(), [2, 5, 8], rtol=2e-3)
    assert RowPrior().medians() is None


def test_seam_columns_scored_with_the_whole_image_scale():
    gt = np.full((4, 16), 10.0)
    pred = np.full((4, 16), 5.0)
    pred[:, [0, 15]] = 10.0  # wrong by 2x at the seam (after scaling by the whole image's median: 2)
    acc = DepthAccumulator(seam_fraction=0.125)  # 1 column at each side of 16
    assert acc.seam_columns(16) == 1 and acc.seam_columns(256) == 16
    assert acc.add(gt, pred, seam=True) == pytest.approx(2.0)
    r = acc.result()
    assert r["seam"]["abs_rel"] == pytest.approx(1.0) and r["seam"]["a1"] == 0 and r["seam"]["n_images"] == 1
    assert r["centre"]["abs_rel"] == pytest.approx(0.0) and r["centre"]["n_images"] == 1
    centre_only = pred.copy()
    centre_only[:, [0, 15]] = 5.0
    centre_only[:, 7:9] = [[10.0, 2.5]] * 4  # columns 7 and 8: the centre band of 16
    c = DepthAccumulator(seam_fraction=0.125)
    c.add(gt, centre_only, seam=True)
    assert c.result()["seam"]["abs_rel"] == pytest.approx(0) and c.result()["centre"]["abs_rel"] > 0.5
    assert r["abs_rel"] == pytest.approx(2 / 16)
    # masked-out seam pixels do not count; images that are not full panoramas have no seam
    gt2 = gt.copy()
    gt2[:, [0, 15]] = 0
    acc.add(gt2, pred, seam=True)
    acc.add(gt, pred, seam=False)
    assert acc.result()["seam"]["n_images"] == 1
    assert DepthAccumulator().add(gt, pred, seam=True) and DepthAccumulator().result()["seam"] is None
    with pytest.raises(InputError, match="seam_fraction"):
        DepthAccumulator(seam_fraction=1.5)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"batch_size": 0}, "batch_size"),
        ({"min_depth": 0.0}, "min_depth"),
        ({"min_depth": 5.0, "max_depth": 2.0}, "min_depth"),
        ({"seam_fraction": -0.1}, "seam_fraction"),
        ({"seam_fraction": 1.5}, "seam_fraction"),
        ({"seam_fraction": math.nan}, "seam_fraction"),
    ],
)
def test_invalid_arguments_are_input_errors_before_any_file_is_read(tmp_path, kwargs, match):
    # checked first: the (empty) dataset would otherwise be the error
    with pytest.raises(InputError, match=match):
        evaluate_depth(_ColumnPredictor(True), tmp_path / "nothing", **kwargs)
    with pytest.raises(InputError, match="yaw_roll"):
        evaluate_depth(str(tmp_path), tmp_path / "nothing", yaw_roll=0)


# --------------------------------------------------------------------------------------- toy dataset
def _toy_dataset(root, train_depth, test_depth):
    """One sequence of 6 frames 16x8: frames 0-2 train with ``train_depth(i)``, 3-5 test."""
    cam = CylindricalCamera.full(16, 8)
    w = SequenceWriter(root / "seq", cam)
    rng = np.random.default_rng(1)
    for i in range(6):
        d = train_depth(i) if i < 3 else test_depth(i)
        w.add_frame(rng.integers(0, 255, (8, 16, 3), dtype=np.uint8), d.astype(np.float32))
    w.finish()
    (root / "splits" / "default").mkdir(parents=True)
    (root / "splits" / "default" / "train.txt").write_text("seq 000000\nseq 000001\nseq 000002\n")
    (root / "splits" / "default" / "test.txt").write_text("seq 000003\nseq 000004\nseq 000005\n")
    return cam


def _write_predictions(pred_root, depth_of):
    for i in range(6):
        d = pred_root / "seq"
        d.mkdir(parents=True, exist_ok=True)
        np.save(d / f"{i:06d}.npy", depth_of(i))


def test_per_row_prior_and_constant_baseline_on_toy_dataset(tmp_path):
    rng = np.random.default_rng(5)
    rows = np.linspace(3, 40, 8)[:, None]
    train = [rows * rng.uniform(0.8, 1.2, (8, 16)) for _ in range(3)]
    test = [np.flipud(rows) * rng.uniform(0.5, 2.0, (8, 16)) for _ in range(3)]  # very different rows
    test[0][:, :3] = 0  # unknown
    _toy_dataset(tmp_path, lambda i: train[i], lambda i: test[i - 3])
    const_pred = tmp_path / "pred"
    _write_predictions(const_pred, lambda i: np.full((4, 8), 3.0, np.float32))  # half size, constant
    r = evaluate_depth(str(const_pred), tmp_path, split="test", prior_split="train")
    assert r["n_images"] == 3 and r["prior_images"] == 3
    # the constant baseline equals scoring a constant map
    for k in DEPTH_METRICS:
        assert r["model"][k] == pytest.approx(r["constant"][k], rel=1e-12)
    # the per-row prior: each row's median over the training frames only
    exact = np.median(np.concatenate(train, 1), axis=1)
    prior_map = np.repeat(exact[:, None], 16, 1)
    want = evaluate_depth_maps([(t, prior_map) for t in test])
    for k in DEPTH_METRICS:
        assert r["per_row"][k] == pytest.approx(want[k], rel=5e-3, abs=1e-3)
    # a perfect prediction directory, with the SEQ/depth/ layout
    perfect = tmp_path / "perfect" / "seq" / "depth"
    perfect.mkdir(parents=True)
    for i in range(6):
        shutil.copy(tmp_path / "seq" / "depth" / f"{i:06d}.npy", perfect / f"{i:06d}.npy")
    r = evaluate_depth(str(tmp_path / "perfect"), tmp_path, split="test")
    assert r["model"]["abs_rel"] == pytest.approx(0, abs=1e-7) and r["model"]["a1"] == 1
    assert r["per_row"]["abs_rel"] > 0.1
    # the seam band of these full panoramas: 2 of 16 columns at each side with a quarter of the width
    assert r["model"]["seam"]["abs_rel"] == pytest.approx(0, abs=1e-7)
    r = evaluate_depth(str(const_pred), tmp_path, split="test", seam_fraction=0.25)
    seam_cols = np.r_[0:2, 14:16]
    want = DepthAccumulator(seam_fraction=0.25)
    for t in test:
        want.add(t, np.ones_like(t), seam=True)
    assert r["constant"]["seam"]["abs_rel"] == pytest.approx(want.result()["seam"]["abs_rel"], rel=1e-6)
    assert r["model"]["seam"]["n_images"] == 3 and len(seam_cols) == 2 * want.seam_columns(16)
    assert evaluate_depth(str(const_pred), tmp_path, split="test", seam_fraction=0)["model"]["seam"] is None


def test_missing_prediction_names_the_file(tmp_path):
    rows = np.linspace(3, 40, 8)[:, None] * np.ones((8, 16))
    _toy_dataset(tmp_path, lambda i: rows, lambda i: rows)
    _write_predictions(tmp_path / "pred", lambda i: rows)
    (tmp_path / "pred" / "seq" / "000004.npy").unlink()
    with pytest.raises(DatasetError, match=r"pred/seq/000004\.npy: prediction not found"):
        evaluate_depth(str(tmp_path / "pred"), tmp_path)
    # frames without a prediction outside the split are not needed
    evaluate_depth(str(tmp_path / "pred"), tmp_path, split="train", prior_split=None)


# --------------------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """2 synthetic sequences x 8 frames at 128x32 (train: one sequence, test: the other) and an untrained
    checkpoint."""
    from cylsfm.data.synth import generate_dataset
    from helpers import untrained_checkpoint

    base = tmp_path_factory.mktemp("evaldepth")
    root = base / "data"
    generate_dataset(root, sequences=2, frames=8, width=128, height=32, seed=3, workers=1, progress=False)
    make_splits(root, mode="sequence", fractions=(0.5, 0.0, 0.5))
    ckpt = untrained_checkpoint(base)
    return root, ckpt


def test_cli_depth_with_checkpoint_writes_json(synth, tmp_path, capsys):
    root, ckpt = synth
    out = tmp_path / "depth.json"
    args = ["evaluate", "depth", "--checkpoint", str(ckpt), "--data", str(root), "--json", str(out)]
    assert main([*args, "--device", "cpu", "--no-progress", "--batch-size", "3"]) == 0
    text = capsys.readouterr().out
    assert "per_row" in text and "model/constant" in text and "model/per_row" in text
    data = json.loads(out.read_text())
    keys = {*DEPTH_METRICS, "n_images", "scale_mean", "scale_std", "seam", "centre"}
    assert keys <= set(data) and set(data) == keys | {"baselines", "meta", "scale_consistency"}
    assert data["scale_consistency"]["rides"] and data["scale_consistency"]["reference"] > 0
    assert "@seam" in text and set(data["seam"]) == {*DEPTH_METRICS, "n_images"}
    assert "@centre" in text and set(data["centre"]) == set(data["seam"])
    assert data["meta"]["seam_fraction"] == pytest.approx(0.125)
    assert data["n_images"] == 6  # the test sequence's targets (frames 1..6)
    assert set(data["baselines"]) == {"constant", "per_row"}
    for name in ("constant", "per_row"):
        assert set(data["baselines"][name]) == keys
    assert data["meta"]["prior_images"] == 6
    assert all(0 <= data[k] <= 1 for k in ("a1", "a2", "a3"))


def test_cli_depth_perfect_and_missing_predictions(synth, tmp_path, capsys):
    root, _ = synth
    pred = tmp_path / "pred"
    for seq in scan_dataset(root):
        (pred / seq.name).mkdir(parents=True)
        for path in seq.depths:
            shutil.copy(path, pred / seq.name / path.name)
    out = tmp_path / "perfect.json"
    args = ["evaluate", "depth", "--predictions", str(pred), "--data", str(root), "--no-progress"]
    assert main([*args, "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["abs_rel"] == pytest.approx(0, abs=1e-6) and data["a1"] == 1
    assert data["baselines"]["constant"]["abs_rel"] > 0.01
    test_seq = (root / "splits" / "default" / "test.txt").read_text().split("\n")[2].split()[0]
    missing = pred / test_seq / "000003.npy"
    missing.unlink()
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


class _ColumnPredictor:
    """A stand-in for :class:`cylsfm.model.Predictor`: depth from the red channel (follows the image
    when it is rolled) or a fixed column profile (knows only where things usually are in the image)."""

    def __init__(self, from_image: bool, profile: np.ndarray | None = None) -> None:
        self.from_image, self.profile = from_image, profile

    def window(self, camera):
        return None

    def depth(self, images: torch.Tensor, camera, mask=None) -> torch.Tensor:
        if self.from_image:
            return 1.0 + 40.0 * images[:, :1].double()
        return torch.from_numpy(self.profile).expand(images.shape[0], 1, *self.profile.shape).clone()


def test_yaw_roll_turns_images_and_ground_truth_together(tmp_path):
    cam = CylindricalCamera.full(16, 8)
    w = SequenceWriter(tmp_path / "seq", cam)
    red = np.tile(np.linspace(0, 255, 16).round().astype(np.uint8), (8, 1))  # depth grows along the width
    for _ in range(6):
        img = np.stack([red, red // 2, red // 3], -1)
        w.add_frame(img, (1.0 + 40.0 * red / 255.0).astype(np.float32))
    w.finish()
    make_splits(tmp_path, mode="frame", fractions=(0.5, 0.0, 0.5), seed=0)
    follows = _ColumnPredictor(True)
    plain = evaluate_depth(follows, tmp_path, split="test")
    rolled = evaluate_depth(follows, tmp_path, split="test", yaw_roll=3)
    assert plain["model"]["abs_rel"] == pytest.approx(0, abs=1e-6)
    assert rolled["model"]["abs_rel"] == pytest.approx(0, abs=1e-6) and rolled["yaw_roll"] == 3
    assert rolled["constant"]["abs_rel"] == pytest.approx(plain["constant"]["abs_rel"], rel=1e-9)
    prior = _ColumnPredictor(False, (1.0 + 40.0 * red / 255.0).astype(np.float64))
    assert evaluate_depth(prior, tmp_path, split="test")["model"]["abs_rel"] == pytest.approx(0, abs=1e-6)
    assert evaluate_depth(prior, tmp_path, split="test", yaw_roll=3)["model"]["abs_rel"] > 0.1
    with pytest.raises(InputError, match="yaw_roll"):
        evaluate_depth(str(tmp_path), tmp_path, split="test", yaw_roll=0)


def test_yaw_roll_turns_the_mask_with_the_panorama(tmp_path):
    cam = CylindricalCamera.full(16, 8)
    w = SequenceWriter(tmp_path / "seq", cam)
    red = np.tile(np.linspace(0, 255, 16).round().astype(np.uint8), (8, 1))
    depth = (1.0 + 40.0 * red / 255.0).astype(np.float32)
    depth[:, 8:] = 0.5  # unknown to any depth range below: only the masked-out half is wrong
    for _ in range(6):
        w.add_frame(np.stack([red, red // 2, red // 3], -1), np.where(depth > 0.5, depth, 3.0))
    keep = np.zeros((8, 16), bool)
    keep[:, :8] = True  # the half whose depth the red channel encodes
    w.finish(mask=keep)
    make_splits(tmp_path, mode="frame", fractions=(0.5, 0.0, 0.5), seed=0)
    follows = _ColumnPredictor(True)
    for roll in (None, 3, 4):
        r = evaluate_depth(follows, tmp_path, split="test", yaw_roll=roll)
        assert r["model"]["abs_rel"] == pytest.approx(0, abs=1e-6)


def test_cli_yaw_roll_needs_a_checkpoint(synth, capsys):
    root, _ = synth
    args = ["evaluate", "depth", "--predictions", str(root), "--data", str(root), "--yaw-roll", "1"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert re.search("yaw[-_]roll", err) and "Traceback" not in err


def test_scale_consistency_over_each_ride(synth, tmp_path, capsys):
    """Predictions of one scale per ride: a coefficient of variation of 0; each frame scaled on its own by
    known factors: exactly their spread; the reference (a per-frame scale) is the spread of the frames'
    median true depths."""
    from cylsfm.evaluate.depth import evaluate_depth

    root, _ = synth
    factors = np.array([1.0, 2.0, 0.5, 1.5, 3.0, 1.0, 2.5, 0.8])
    runs = {}
    for name, per_frame in (("steady", False), ("wobbly", True)):
        pred = tmp_path / name
        for seq in scan_dataset(root):
            (pred / seq.name).mkdir(parents=True)
            for i, path in enumerate(seq.depths):
                f = factors[i] if per_frame else 3.0
                np.save(pred / seq.name / path.name, np.load(path) * f)
        runs[name] = evaluate_depth(pred, root, split=None, prior_split=None)["scale_consistency"]
    assert runs["steady"]["model"] == pytest.approx(0, abs=1e-6)  # (float32 files)
    scales = 1 / factors
    for ride in runs["wobbly"]["rides"].values():
        assert ride["model"] == pytest.approx(scales.std() / scales.mean(), rel=1e-6)
        assert ride["frames"] == 8 and ride["reference"] > 0
    valid = [(d := np.load(p))[(d > 1e-3) & (d < 80)] for p in scan_dataset(root)[0].depths]  # scored pixels
    medians = [float(np.median(v)) for v in valid]
    first = runs["steady"]["rides"][scan_dataset(root)[0].name]
    assert first["reference"] == pytest.approx(np.std(medians) / np.mean(medians), rel=1e-6)
    args = [
        "evaluate",
        "depth",
        "--predictions",
        str(tmp_path / "wobbly"),
        "--data",
        str(root),
        "--no-progress",
    ]
    assert main(args) == 0
    assert "scale over each ride" in capsys.readouterr().out
