import json

from cylsfm.cli import main


def test_demo_runs_end_to_end_and_writes_a_report(tmp_path, capsys):
    """A tiny budget: generate, train a few steps, evaluate against the baselines, write the report."""
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--minutes", "2.15", "--size", "128x32", "--sequences", "4"]
    assert main([*args, "--test-sequences", "1", "--frames", "12", "--no-progress"]) == 0
    report = (out / "report.md").read_text()
    assert "per_row" in report and "constant velocity" in report and "figures/loss.png" in report
    depth = json.loads((out / "depth.json").read_text())
    assert {"abs_rel", "a1"} <= set(depth) and {"constant", "per_row"} <= set(depth["baselines"])
    pose = json.loads((out / "pose.json").read_text())
    assert "ate_mean" in pose and "constant_velocity" in pose["baselines"]
    assert (out / "figures" / "loss.png").exists()
    assert "abs_rel" in capsys.readouterr().out
