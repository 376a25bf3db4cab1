import json
import math
import re

import matplotlib
import numpy as np
import pytest

from cylsfm.cli import main
from cylsfm.data.format import load_image
from cylsfm.model import load_models

TERMS = ("photometric", "smooth", "explain", "total")


def _finite_numbers(tree) -> list[float]:
    """Every number in a JSON tree (strings and lists of paths are skipped)."""
    if isinstance(tree, dict):
        return [x for v in tree.values() for x in _finite_numbers(v)]
    if isinstance(tree, list):
        return [x for v in tree for x in _finite_numbers(v)]
    return [float(tree)] if isinstance(tree, int | float) and not isinstance(tree, bool) else []


def _split(path) -> list[tuple[str, str]]:
    lines = [line.split() for line in path.read_text().splitlines() if line and not line.startswith("#")]
    return [(seq, frame) for seq, frame in lines]


def test_demo_runs_end_to_end_and_writes_a_report(tmp_path, capsys):
    """A tiny budget: generate, train a few steps, evaluate against the baselines, write the report."""
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--minutes", "2.15", "--size", "128x32", "--sequences", "4"]
    assert main([*args, "--test-sequences", "1", "--frames", "12", "--no-progress"]) == 0
    printed = capsys.readouterr().out

    # data: four rides of twelve frames, one of them held out for the test
    data = out / "data"
    assert sorted(p.name for p in data.glob("seq_*")) == [f"seq_{i:03d}" for i in range(4)]
    assert all(len(list(p.glob("images/*.png"))) == 12 for p in data.glob("seq_*"))
    test = _split(data / "splits" / "default" / "test.txt")
    train = _split(data / "splits" / "default" / "train.txt")
    test_seqs = {seq for seq, _ in test}
    assert len(test_seqs) == 1 and not test_seqs & {seq for seq, _ in train}

    # training: the model trained is the one asked for, and its log is sane
    models = load_models(out / "run")
    cfg = models.config
    assert (cfg.data.width, cfg.data.height, cfg.data.root, cfg.data.split) == (128, 32, str(data), "train")
    assert cfg.preset == "default" and cfg.pose_head == "equivariant" and cfg.wrap and cfg.model.compass
    assert cfg.model.antisymmetric and cfg.model.scaffold
    rows = [json.loads(line) for line in (out / "run" / "metrics.jsonl").read_text().splitlines()]
    steps = [r["step"] for r in rows]
    assert steps[0] == 1 and steps == sorted(set(steps)) and steps[-1] <= models.step
    for row in rows:
        assert all(math.isfinite(row[k]) for k in TERMS), row
        parts = row["photometric"] + row["smooth"] + row["explain"] + row.get("scaffold", 0.0)
        assert row["total"] == pytest.approx(parts, rel=1e-6)
        assert row["photometric"] > 0
    report = (out / "report.md").read_text()
    assert re.search(rf"\b{models.step} steps in", report)

    # evaluation: on every frame of the held-out ride, all numbers finite, the tables printed as saved
    depth = json.loads((out / "depth.json").read_text())
    pose = json.loads((out / "pose.json").read_text())
    assert depth["n_images"] == len(test)
    assert set(pose["sequences"]) == test_seqs and pose["n_snippets"] > 0
    assert all(math.isfinite(x) for x in _finite_numbers(depth) + _finite_numbers(pose))
    assert 0 < depth["abs_rel"] and 0 <= depth["a1"] <= depth["a2"] <= depth["a3"] <= 1
    assert {"constant", "per_row"} <= set(depth["baselines"])
    assert {"zero_motion", "constant_velocity"} <= set(pose["baselines"])
    for text in (report, printed):
        model_row = re.search(r"^model +([0-9.]+) ", text, re.MULTILINE)
        assert model_row and float(model_row.group(1)) == pytest.approx(depth["abs_rel"], abs=5e-5)
        assert "per_row" in text and "constant velocity" in text

    # pictures: the loss curve, and for held-out frames input, prediction and ground truth stacked
    pictures = re.findall(r"!\[[^\]]*\]\((figures/[^)]+\.png)\)", report)
    assert "figures/loss.png" in pictures and len(pictures) == 1 + 4
    for name in pictures:
        picture = np.asarray(load_image(out / name))
        if name != "figures/loss.png":
            assert name.split("/")[1].rsplit("_", 1)[0] in test_seqs
            # readable: the 128x32 frames enlarged 8 times to 1024 pixels wide, three panels of 256 rows
            # (input, prediction, ground truth), each under a 16-row title, then the colour scale
            assert picture.shape[1] == 1024 and picture.shape[0] >= 3 * (16 + 2 + 256 + 2)
            assert picture[18 : 18 + 256].std() > 0  # a real input under its title
            lut = np.round(matplotlib.colormaps["magma"](np.linspace(0, 1, 256))[:, :3] * 255).astype(
                np.uint8
            )
            ramp = lut[np.linspace(0, 255, 1024).round().astype(int)]
            bar = np.flatnonzero((picture == ramp[None]).all(axis=2).mean(axis=1) > 0.95)
            assert (
                len(bar) >= 10 and bar.min() > 3 * (16 + 2 + 256 + 2) - 2
            )  # the colour scale, at the bottom
    assert "labelled in metres" in report
