"""Training on SfMLearner strip datasets, and what a resumed run takes from the command line."""

import json
import math

import numpy as np
from PIL import Image

from cylsfm.cli import main
from cylsfm.model import load_models

W, H, N = 128, 32, 3


def _write_strips(root, count=4):
    """``count`` strips of 3 frames of a textured panorama turning by a few columns per frame."""
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (H, 2 * W, 3), dtype=np.uint8)
    lines = []
    for i in range(count):
        frames = [np.roll(base, 2 * (i + j), axis=1)[:, :W] for j in range(N)]
        (root / "drive").mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.concatenate(frames, axis=1)).save(root / "drive" / f"{i:04d}.png")
        fx = W / (2 * math.pi)
        (root / "drive" / f"{i:04d}_cam.txt").write_text(f"{fx},0,{W / 2},0,{H / 2},{(H - 1) / 2},0,0,1\n")
        lines.append(f"drive {i:04d}")
    (root / "train.txt").write_text("\n".join(lines) + "\n")


def test_train_reads_sfmlearner_strips(tmp_path):
    data, run = tmp_path / "strips", tmp_path / "run"
    _write_strips(data)
    argv = ["train", "--data", str(data), "--out", str(run), "--size", f"{W}x{H}", "--max-steps", "2"]
    argv += ["--batch-size", "2", "--workers", "0", "--no-progress", "log_every=1"]
    assert main(argv) == 0
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2]
    assert all(math.isfinite(r["total"]) and r["total"] > 0 for r in rows)
    models = load_models(run)
    assert models.step == 2 and models.config.data.root == str(data)


def test_resume_keeps_the_run_and_warns_about_ignored_settings(tmp_path):
    """A resumed run takes a new budget and data root, keeps everything else and says what it ignored."""
    import pytest

    from cylsfm.model.config import apply_overrides, preset
    from cylsfm.train.trainer import train

    data, run = tmp_path / "strips", tmp_path / "run"
    _write_strips(data)
    base = [f"data.root='{data}'", f"data.width={W}", f"data.height={H}", "data.workers=0", "batch_size=2"]
    train(apply_overrides(preset("default"), [*base, "max_steps=1"]), run, progress=False)
    moved = tmp_path / "moved"
    data.rename(moved)
    asked = apply_overrides(
        preset("default"),
        [*base, f"data.root='{moved}'", "max_steps=2", "loss.ssim_weight=0.5", "batch_size=3"],
    )
    with pytest.warns(UserWarning, match=r"ignored: .*loss.ssim_weight.*batch_size|batch_size.*ssim"):
        summary = train(asked, run, resume=True, progress=False)
    assert summary["steps"] == 2
    cfg = load_models(run).config
    assert cfg.data.root == str(moved) and cfg.loss.ssim_weight == preset("default").loss.ssim_weight
    assert cfg.batch_size == 2
