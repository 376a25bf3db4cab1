"""The ride exports on top of the odometry pipeline: the model is loaded once per command, a finished
odometry output is reused (and refused when its settings differ), and every option of ``cylsfm odometry``
reaches the exports."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from cylsfm.cli import build_parser, main
from cylsfm.data.io import read_tum
from cylsfm.data.synth import generate_dataset
from cylsfm.model import build as model_build

pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def ride(tmp_path_factory):
    root = tmp_path_factory.mktemp("exports")
    generate_dataset(
        root / "data", sequences=1, frames=6, width=128, height=32, seed=5, workers=1, progress=False
    )
    return root / "data" / "seq_000"


def _colmap(ride, out, ckpt, *extra) -> list[str]:
    args = ["export", "colmap", str(ride), str(out), "--checkpoint", str(ckpt), "--view-size", "32"]
    return [*args, "--points-per-frame", "50", "--device", "cpu", "--no-progress", *map(str, extra)]


@pytest.fixture
def loads(monkeypatch) -> list[str]:
    """The checkpoints loaded from now on (every load goes through ``load_models``)."""
    seen: list[str] = []
    real = model_build.load_models

    def counting(path, *args, **kwargs):
        seen.append(str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(model_build, "load_models", counting)
    import cylsfm.model.predictor as predictor_module

    monkeypatch.setattr(predictor_module, "load_models", counting)
    return seen


def test_an_export_loads_the_model_once_and_reuses_a_given_odometry(ckpt, ride, tmp_path, loads, capsys):
    out = tmp_path / "odo"
    opts = ["--refine", "--keyframes", "2", "--mount-yaw", "30", "--no-loops"]
    args = ["odometry", str(ride), "--checkpoint", str(ckpt), "--out", str(out), "--device", "cpu"]
    assert main([*args, "--no-progress", *opts]) == 0
    assert len(loads) == 1
    # the export runs its own odometry: one load, the same trajectory as cylsfm odometry's
    assert main(_colmap(ride, tmp_path / "own", ckpt, *opts)) == 0
    assert len(loads) == 2
    _, mine = read_tum(tmp_path / "own" / "odometry" / "trajectory.txt")
    _, theirs = read_tum(out / "trajectory.txt")
    np.testing.assert_allclose(mine, theirs, atol=1e-9)
    # given the finished output: one load, nothing tracked again, the same model written
    assert main(_colmap(ride, tmp_path / "given", ckpt, "--odometry", out, *opts)) == 0
    assert len(loads) == 3
    assert not (tmp_path / "given" / "odometry").exists()
    import pycolmap

    a = pycolmap.Reconstruction(str(tmp_path / "own" / "sparse" / "0"))
    b = pycolmap.Reconstruction(str(tmp_path / "given" / "sparse" / "0"))
    assert a.num_images() == b.num_images() > 0
    for image_id, image in a.images.items():
        np.testing.assert_allclose(
            image.cam_from_world().matrix(), b.images[image_id].cam_from_world().matrix(), atol=1e-6
        )
    capsys.readouterr()
    # other settings than the output's: refused, naming what differs
    assert main(_colmap(ride, tmp_path / "other", ckpt, "--odometry", out, "--refine", "--no-loops")) == 2
    err = capsys.readouterr().err
    assert "other settings" in err and "keyframe_every" in err and "mount_yaw" in err, err
    assert not (tmp_path / "other" / "sparse").exists()
    # no odometry there
    assert main(_colmap(ride, tmp_path / "none", ckpt, "--odometry", tmp_path / "missing")) == 2
    assert "odometry.json: not found" in capsys.readouterr().err


def test_the_fingerprint_covers_what_changes_the_trajectory(ckpt, ride, tmp_path):
    """Options that change the written trajectory change the fingerprint an export checks; the depth
    files written or not do not."""
    from dataclasses import replace

    from cylsfm.odometry import OdometrySettings, resolve_job

    base = OdometrySettings(device="cpu", progress=False)
    fp = resolve_job(ride, ckpt, tmp_path, base).fingerprint
    assert resolve_job(ride, ckpt, tmp_path, replace(base, save_depth_maps=True)).fingerprint == fp
    for change in (
        {"refine": True},
        {"camera_height": 1.5},
        {"steady_height": True},
        {"loops": False},
        {"keyframe_every": 3},
        {"mount_yaw": 10.0},
        {"stride": 2},
        {"mask": False},
    ):
        other = resolve_job(ride, ckpt, tmp_path, replace(base, **change)).fingerprint
        assert other != fp or change == {"mask": False}, change


def _dests(parser: argparse.ArgumentParser, *path: str) -> set[str]:
    for name in path:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return {a.dest for a in parser._actions if a.dest != "help"}


def test_every_odometry_option_reaches_the_exports_of_a_ride():
    parser = build_parser()
    odometry = _dests(parser, "odometry") - {"out", "depth"}  # its own output folder and depth files
    for export in ("colmap", "rerun"):
        assert odometry <= _dests(parser, "export", export), odometry - _dests(parser, "export", export)


def test_an_export_and_the_odometry_read_the_same_settings_from_the_same_options():
    from cylsfm.cli.odometry import ride_settings

    parser = build_parser()
    opts = ["--refine", "--keyframes", "3", "--mount-yaw", "-20", "--no-loops", "--steady-height"]
    opts += ["--pose-iterations", "1", "--camera-height", "1.6", "--stride", "2", "--no-mask", "--no-amp"]
    odo = parser.parse_args(["odometry", "ride", "--checkpoint", "c", "--out", "o", *opts])
    exp = parser.parse_args(["export", "rerun", "ride", "o.rrd", "--checkpoint", "c", *opts])
    assert ride_settings(odo) == ride_settings(exp)
    s = ride_settings(exp)
    assert (s.keyframe_every, s.mount_yaw, s.loops, s.pose_iterations, s.mask, s.amp) == (
        3,
        -20.0,
        False,
        1,
        False,
        False,
    )
    assert json.dumps(str(s))  # printable


def test_the_bundle_adjustment_comes_with_the_refinement_unless_turned_off():
    from cylsfm.cli.odometry import ride_settings
    from cylsfm.errors import InputError
    from cylsfm.odometry import OdometrySettings

    parser = build_parser()
    for command in (["odometry", "ride", "--out", "o"], ["export", "colmap", "ride", "o"]):

        def adjusts(*opts, command=command):
            return ride_settings(parser.parse_args([*command, "--checkpoint", "c", *opts])).adjusts

        assert adjusts("--refine") and adjusts("--bundle") and adjusts("--refine", "--bundle")
        assert not adjusts() and not adjusts("--refine", "--no-bundle")
    assert OdometrySettings(refine=True).adjusts and not OdometrySettings(refine=True, bundle=False).adjusts
    with pytest.raises(InputError, match="bundle must be"):
        OdometrySettings(bundle="yes")
