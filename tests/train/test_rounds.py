"""Training in rounds over the rides' own adjusted geometry (cylsfm.rounds, ``train --sfm-rounds``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import cylsfm.rounds as rounds
from cylsfm.data.geometry import load_geometry
from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera
from cylsfm.model import load_checkpoint
from cylsfm.rounds import STATE_FILE, geometry_dir, train_rounds
from helpers import tiny_training_config


def _cfg(root, **extra):
    base = {"max_steps": 4, "sfm.rounds": 1, "sfm.refine": "false"}
    return tiny_training_config(root, **(base | extra))


def _weights(run):
    state = load_checkpoint(run)
    return {k: v.clone() for k, v in state["disp_net"].items()} | {
        "pose." + k: v.clone() for k, v in state["pose_net"].items()
    }


def test_a_round_trains_adjusts_every_ride_and_trains_on_with_its_geometry(tiny_data, tmp_path):
    run = tmp_path / "run"
    done = train_rounds(_cfg(tiny_data), run, progress=False)
    assert [s["stage"] for s in done["stages"]] == ["train", "geometry", "train"]
    assert [s.get("steps") for s in done["stages"]] == [2, None, 4] and done["steps"] == 4
    rides = sorted(p.name for p in tiny_data.iterdir() if p.name.startswith("seq_"))
    assert done["stages"][1]["rides"] == dict.fromkeys(rides, "ok")
    for ride in rides:  # the geometry is the ride's own: readable as targets, one pose a frame
        cam = CylindricalCamera.from_json(tiny_data / ride / "camera.json")
        geo = load_geometry(geometry_dir(run, 1) / ride, 10, cam)
        assert geo.c2w.shape == (10, 4, 4) and len(geo.depth) > 0
        # the odometry wrote every frame's depth (the fused depth is on by default): each frame has its own
        stems = sorted(p.stem for p in (tiny_data / ride / "images").iterdir())
        assert sorted(p.stem for p in (geometry_dir(run, 1) / ride / "depth").glob("*.npy")) == stems
        fused = load_geometry(geometry_dir(run, 1) / ride, 10, cam, stems).fused
        assert fused is not None and (fused[:, 0] > 0).mean() > 0.5
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert all("sfm_depth" not in r for r in rows if r["step"] <= 2)
    later = [r for r in rows if r["step"] > 2]
    assert later and all(r["sfm_depth"] > 0 and r["sfm_pose"] > 0 and r["sfm_dense"] > 0 for r in later)
    parts = sum(
        later[-1].get(k, 0.0)
        for k in ("photometric", "smooth", "explain", "scaffold", "sfm_depth", "sfm_pose", "sfm_dense")
    )
    assert later[-1]["total"] == pytest.approx(parts, rel=1e-6)
    saved = json.loads((run / STATE_FILE).read_text())
    assert len(saved["stages"]) == 3 and saved["seconds"] > 0


def test_a_run_interrupted_between_rounds_resumes_to_the_same_weights(tiny_data, tmp_path, monkeypatch):
    train_rounds(_cfg(tiny_data), tmp_path / "straight", progress=False)
    real = rounds.odometry

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(rounds, "odometry", killed)
    with pytest.raises(KeyboardInterrupt):
        train_rounds(_cfg(tiny_data), tmp_path / "split", progress=False)
    assert len(json.loads((tmp_path / "split" / STATE_FILE).read_text())["stages"]) == 1
    with pytest.raises(Exception, match="already holds a run"):
        train_rounds(_cfg(tiny_data), tmp_path / "split", progress=False)
    monkeypatch.setattr(rounds, "odometry", real)
    done = train_rounds(_cfg(tiny_data), tmp_path / "split", resume=True, progress=False)
    assert [s["stage"] for s in done["stages"]] == ["train", "geometry", "train"]
    a, b = _weights(tmp_path / "straight"), _weights(tmp_path / "split")
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    for name in ("trajectory.txt",):
        ride = sorted(p.name for p in tiny_data.iterdir() if p.name.startswith("seq_"))[0]
        assert np.array_equal(
            np.loadtxt(geometry_dir(tmp_path / "straight", 1) / ride / name),
            np.loadtxt(geometry_dir(tmp_path / "split", 1) / ride / name),
        )


def test_the_budget_is_shared_after_each_pass():
    from cylsfm.model.config import apply_overrides, preset

    cfg = apply_overrides(
        preset("default"), ["minutes=10", "max_steps=1000", "sfm.rounds=2", "sfm.first_share=0.4"]
    )
    plan = rounds._stages(2)
    first = rounds._training_config(cfg, rounds.Path("r"), {"stages": [], "seconds": 0.0}, plan, 0)
    assert (first.minutes, first.max_steps, first.data.geometry) == (4.0, 400, None)
    state = {"stages": [{"stage": "train"}, {"stage": "geometry", "seconds": 60.0}], "seconds": 300.0}
    second = rounds._training_config(cfg, rounds.Path("r"), state, plan, 2)
    # 600 s - 300 spent - one more pass of 60 s, in two stages: 120 s each
    assert second.minutes == pytest.approx(2.0) and second.max_steps == 700
    assert second.data.geometry == str(rounds.Path("r/geometry/round_1")) and second.loss.sfm_depth_weight > 0


def test_the_command_resumes_the_whole_run_not_the_stage_it_stopped_in(
    tiny_data, tmp_path, monkeypatch, capsys
):
    """``train --resume`` of a run in rounds continues the plan recorded when it started (the stage's own
    ``config.yaml`` holds only its share of the budget)."""
    from cylsfm.cli import main

    run = tmp_path / "run"
    args = ["train", "--data", str(tiny_data), "--out", str(run), "--size", "128x32", "--max-steps", "4"]
    args += ["--sfm-rounds", "1", "--split", "all", "--workers", "0", "--batch-size", "2", "--no-progress"]
    args += ["sfm.refine=false", "latest_every=1", "checkpoint_every=0"]
    real = rounds.odometry

    def killed(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(rounds, "odometry", killed)
    assert main(args) == 130
    assert load_checkpoint(run)["step"] == 2
    monkeypatch.setattr(rounds, "odometry", real)
    assert main(["train", "--out", str(run), "--resume", "--no-progress"]) == 0
    assert load_checkpoint(run)["step"] == 4
    assert "trained to step 4 in rounds (done)" in capsys.readouterr().out
    stages = json.loads((run / STATE_FILE).read_text())["stages"]
    assert [s["stage"] for s in stages] == ["train", "geometry", "train"]


def test_a_ride_without_geometry_is_trained_on_without_targets(tiny_data, tmp_path, monkeypatch):
    rides = sorted(p.name for p in tiny_data.iterdir() if p.name.startswith("seq_"))
    real = rounds.odometry

    def first_fails(ride, checkpoint, out, settings):
        if ride.name == rides[0]:
            out.mkdir(parents=True)  # the odometry makes its folder before it finds the ride too short
            (out / "odometry_state.json").write_text("{}")
            raise CylsfmError(f"{ride}: 3 frames; a trajectory needs at least 4")
        return real(ride, checkpoint, out, settings)

    monkeypatch.setattr(rounds, "odometry", first_fails)
    run = tmp_path / "run"
    with pytest.warns(UserWarning, match="no geometry this round"):
        done = train_rounds(_cfg(tiny_data), run, progress=False)
    assert done["steps"] == 4 and done["stages"][1]["rides"][rides[1]] == "ok"
    assert "needs at least 4" in done["stages"][1]["rides"][rides[0]]
    assert not (geometry_dir(run, 1) / rides[0]).exists()
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert all(r["step"] <= 2 or "sfm_depth" in r for r in rows)


def test_a_run_in_rounds_is_not_started_over_by_accident(tiny_data, tmp_path):
    run = tmp_path / "run"
    train_rounds(_cfg(tiny_data, max_steps=2, **{"sfm.rounds": 0}), run, progress=False)
    with pytest.raises(CylsfmError, match="already holds a run"):
        train_rounds(_cfg(tiny_data), run, progress=False)
    (run / "geometry" / "round_1" / "old").mkdir(parents=True)
    done = train_rounds(_cfg(tiny_data), run, progress=False, overwrite=True)
    assert done["steps"] == 4 and not (run / "geometry" / "round_1" / "old").exists()
