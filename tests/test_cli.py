import json
import math
import subprocess
import sys

import pytest

from cylsfm import __version__
from cylsfm.cli import build_parser, main, train_config_from_args
from cylsfm.model.config import apply_overrides, preset, save_config


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert __version__ in capsys.readouterr().out
    assert main([]) == 0
    assert "camera" in capsys.readouterr().out


def test_console_script_runs():
    out = subprocess.run(
        [sys.executable, "-m", "cylsfm.cli", "--help"], capture_output=True, text=True, check=True
    )
    assert "demo" in out.stdout


def test_camera_new_and_show(tmp_path, capsys):
    path = tmp_path / "camera.json"
    assert main(["camera", "new", str(path), "--width", "512", "--height", "128"]) == 0
    data = json.loads(path.read_text())
    assert data["model"] == "cylindrical" and data["width"] == 512 and data["cx"] == 256
    assert main(["camera", "show", str(path)]) == 0
    assert "wraps" in capsys.readouterr().out


def test_bad_camera_file_is_one_clear_line(tmp_path, capsys):
    bad = tmp_path / "camera.json"
    bad.write_text('{"model": "cylindrical", "width": 512}')
    assert main(["camera", "show", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "missing key" in err and "Traceback" not in err


def test_camera_new_writes_each_model(tmp_path, capsys):
    equi = tmp_path / "equirect.json"
    assert (
        main(["camera", "new", str(equi), "--model", "equirectangular", "--width", "256", "--height", "128"])
        == 0
    )
    data = json.loads(equi.read_text())
    assert data["model"] == "equirectangular" and data["fx"] * 2 * math.pi == pytest.approx(256)
    assert data["fy"] * math.pi == pytest.approx(128)  # the whole sphere: rows span +-90 degrees
    pin = tmp_path / "pinhole.json"
    assert main(["camera", "new", str(pin), "--model", "pinhole", "--width", "100", "--height", "80"]) == 2
    assert "--hfov" in capsys.readouterr().err and not pin.exists()
    assert (
        main(
            [
                "camera",
                "new",
                str(pin),
                "--model",
                "pinhole",
                "--width",
                "100",
                "--height",
                "80",
                "--hfov",
                "90",
            ]
        )
        == 0
    )
    assert json.loads(pin.read_text())["fx"] == pytest.approx(50.0)  # tan(45 deg) = 1: f = W / 2
    args = ["camera", "new", str(pin), "--model", "pinhole", "--width", "100", "--height", "80"]
    assert main([*args, "--focal", "123.5"]) == 0
    assert json.loads(pin.read_text())["fx"] == pytest.approx(123.5)
    assert main([*args, "--focal", "100", "--hfov", "90"]) == 2 and "--focal" in capsys.readouterr().err
    assert main([*args, "--focal", "-3"]) == 2 and "positive" in capsys.readouterr().err


def test_synth_writes_its_split_by_sequence_and_keeps_what_exists(tmp_path, capsys):
    out = tmp_path / "data"
    args = ["synth", str(out), "--sequences", "3", "--frames", "3", "--width", "128", "--height", "32"]
    assert main([*args, "--workers", "1", "--split", "1,1,1"]) == 0
    parts = {}
    for part in ("train", "val", "test"):
        lines = (out / "splits" / "default" / f"{part}.txt").read_text().splitlines()
        parts[part] = {line.split()[0] for line in lines if line and not line.startswith("#")}
    assert all(len(seqs) == 1 for seqs in parts.values())  # whole rides, one in each part
    assert set.union(*parts.values()) == {"seq_000", "seq_001", "seq_002"}
    capsys.readouterr()
    before = (out / "seq_000" / "images" / "000000.png").stat().st_mtime_ns
    assert main([*args, "--workers", "1"]) == 2  # the library refuses to replace a sequence
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "seq_000" in err and "overwrite" in err
    assert (out / "seq_000" / "images" / "000000.png").stat().st_mtime_ns == before
    assert main(["synth", str(tmp_path / "x"), "--frames", "2"]) == 2  # checked by generate_dataset
    assert "frames" in capsys.readouterr().err and not (tmp_path / "x").exists()
    with pytest.raises(SystemExit):
        main([*args, "--split", "1,1"])


def test_split_writes_the_parts_and_keeps_what_exists(tmp_path, capsys):
    out = tmp_path / "data"
    synth = ["synth", str(out), "--sequences", "4", "--frames", "8", "--width", "128", "--height", "32"]
    assert main([*synth, "--workers", "1", "--split", "none"]) == 0
    assert not (out / "splits").exists()
    capsys.readouterr()
    # training without split files names the command that writes them
    assert main(["train", "--data", str(out), "--out", str(tmp_path / "run"), "--max-steps", "1"]) == 2
    assert f"cylsfm split {out}" in capsys.readouterr().err
    assert main(["split", str(out), "--mode", "frame", "--preset", "headcam", "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert "frame split" in printed and "val 0" in printed
    parts = {}
    for part in ("train", "val", "test"):
        lines = (out / "splits" / "default" / f"{part}.txt").read_text().splitlines()
        parts[part] = {tuple(line.split()) for line in lines if line and not line.startswith("#")}
    assert parts["test"] and parts["train"] and not parts["val"]
    # the paper's rule: no test snippet (the target and its neighbours) shares a frame with training targets
    near = {(seq, f"{int(stem) + d:06d}") for seq, stem in parts["test"] for d in (-2, -1, 0, 1, 2)}
    assert not near & parts["train"]
    before = (out / "splits" / "default" / "test.txt").read_text()
    assert main(["split", str(out)]) == 2 and "--force" in capsys.readouterr().err
    assert (out / "splits" / "default" / "test.txt").read_text() == before
    assert main(["split", str(out), "--force", "--fractions", "0.5", "0.25", "0.25"]) == 0
    assert "sequence split" in capsys.readouterr().out
    assert main(["split", str(out), "--force", "--fractions", "0.5", "0.5", "0.5"]) == 2
    assert "fractions" in capsys.readouterr().err


def test_resume_takes_the_runs_saved_configuration(tmp_path, capsys):
    """``train --out RUN --resume`` starts from RUN/config.yaml: data root, budget and the rest, unless a flag
    or an override changes them; a preset or --config given explicitly replaces it."""
    run = tmp_path / "run"
    run.mkdir()
    saved = apply_overrides(
        preset("paper-synthia"),
        ["data.root='rides'", "minutes=7", "max_steps=5", "batch_size=3", "data.width=256"],
    )
    save_config(saved, run / "config.yaml")
    parser = build_parser()
    cfg = train_config_from_args(
        parser.parse_args(["train", "--out", str(run), "--resume", "--max-steps", "9"])
    )
    assert (cfg.preset, cfg.data.root, cfg.minutes, cfg.batch_size, cfg.data.width) == (
        "paper-synthia", "rides", 7, 3, 256,
    )  # fmt: skip
    assert cfg.max_steps == 9 and cfg.loss == saved.loss
    cfg = train_config_from_args(parser.parse_args(["train", "--out", str(run), "--resume", "minutes=null"]))
    assert cfg.minutes is None and cfg.max_steps == 5
    cfg = train_config_from_args(
        parser.parse_args(["train", "--out", str(run), "--resume", "--preset", "improved"])
    )
    assert cfg.preset == "improved" and cfg.data.root == ""
    # without --resume a run directory's old configuration is not used
    assert main(["train", "--out", str(run)]) == 2
    assert "no training data" in capsys.readouterr().err
    # with --resume but nothing to resume: one line naming the missing checkpoint
    assert main(["train", "--out", str(run), "--resume", "--device", "cpu"]) == 2
    assert "nothing to resume" in capsys.readouterr().err


def test_library_argument_errors_are_one_line(tmp_path, capsys):
    """Invalid values the library checks (InputError) reach the user as one line, without a traceback."""
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--sequences", "3", "--test-sequences", "2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--sequences" in err and "Traceback" not in err
    assert not out.exists()


def test_train_help_states_the_defaults_of_the_default_preset(capsys):
    """The defaults printed by ``cylsfm train --help`` are those of the default preset (they cannot drift)."""
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    d = preset("default")
    for shown in (
        f"default {d.data.width}x{d.data.height}",
        f"default {d.batch_size})",
        f"default {d.max_steps})",
        f"seed (default {d.seed})",
        "multiple of 128",
        "default (the default)",
    ):
        assert shown in text, shown
    assert d.data.workers is None and d.minutes is None and d.preset == "default"


def test_print_config_prints_the_resolved_configuration(tmp_path, capsys):
    import yaml

    assert main(["train", "--out", str(tmp_path / "r"), "--size", "256x64", "--print-config", "seed=3"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["data"]["width"] == 256 and printed["seed"] == 3 and printed["preset"] == "default"
    assert printed["model"]["antisymmetric"] is True
    assert not (tmp_path / "r").exists()  # nothing trained, nothing written
