import json
import math
import os
import subprocess
import sys
import warnings

import pytest
import torch

from cylsfm.cli import main
from cylsfm.geometry import CylindricalCamera
from cylsfm.model import CheckpointError, Predictor, load_checkpoint, load_models, save_checkpoint
from cylsfm.model.config import apply_overrides, load_config, preset
from cylsfm.train.trainer import NonFiniteLossError, Trainer, train
from helpers import tiny_training_config


def _cfg(root, **extra):
    return tiny_training_config(root, **extra)


def _weights(run):
    state = load_checkpoint(run)
    return {k: v.clone() for k, v in state["disp_net"].items()} | {
        "pose." + k: v.clone() for k, v in state["pose_net"].items()
    }


TERMS = ("photometric", "smooth", "explain", "total")


def _metrics(run):
    """The rows of ``RUN/metrics.jsonl``, checked: every loss term present and finite, total = sum of terms."""
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    for row in rows:
        assert set(TERMS) | {"step", "translation_norm", "samples_per_s"} <= set(row), row
        assert all(math.isfinite(row[k]) for k in (*TERMS, "translation_norm")), row
        parts = sum(row.get(k, 0.0) for k in ("photometric", "smooth", "explain", "scaffold", "still"))
        assert row["total"] == pytest.approx(parts, rel=1e-6)
    return rows


def _tensorboard(run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tb"), size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    return events


def test_training_writes_config_logs_and_checkpoints(tiny_data, tmp_path):
    run = tmp_path / "run"
    cfg = _cfg(tiny_data, max_steps=3)
    summary = train(cfg, run, progress=False)
    assert summary["steps"] == 3 and summary["stopped"] == "max_steps"
    # metrics: every step logged (log_every=1), every term finite; the default recipe's terms are live
    rows = _metrics(run)
    assert [r["step"] for r in rows] == [1, 2, 3]
    assert all(r["photometric"] > 0 and r["smooth"] > 0 and r["explain"] == 0 for r in rows)
    # TensorBoard holds the same losses, and the target picture (image_every=2) at the training size
    events = _tensorboard(run)
    logged = [(e.step, e.value) for e in events.Scalars("loss/total")]
    assert logged == [(r["step"], pytest.approx(r["total"], rel=1e-6)) for r in rows]
    [image] = events.Images("target")
    assert (image.step, image.width, image.height) == (2, 128, 32)
    # the saved configuration is the one trained, in config.yaml and in the checkpoint alike
    models = load_models(run)  # a run directory means its latest checkpoint
    assert models.step == 3
    assert load_config(run / "config.yaml") == models.config
    assert (models.config.data.width, models.config.data.height, models.config.max_steps) == (128, 32, 3)
    assert models.config.loss == cfg.loss
    # the panoramas' measured extent is run metadata, in the checkpoint beside the configuration
    assert models.dataset == {"vfov_h": 1.0} and "vfov_h" not in (run / "config.yaml").read_text()
    # the weights were trained: every parameter moved away from its (seeded) initialisation
    fresh = Trainer(_cfg(tiny_data, max_steps=3), tmp_path / "fresh")
    fresh.close()
    initial = fresh.model.disp_net.state_dict() | {
        "pose." + k: v for k, v in fresh.model.pose_net.state_dict().items()
    }
    trained = _weights(run)
    assert initial.keys() == trained.keys()
    # (but the pair network's last bias: it cancels in g(t, s) - g(s, t), its gradient is zero but for
    # rounding, which bf16 may not leave)
    dead = {"pose.net.pair.head.conv.bias"}
    assert dead <= trained.keys()
    assert all(not torch.equal(initial[k], trained[k]) for k in trained.keys() - dead), [
        k for k in trained.keys() - dead if torch.equal(initial[k], trained[k])
    ]


def test_resume_continues_exactly(tiny_data, tmp_path):
    """3 + 3 steps with a resume in between give the same weights as 6 steps in one go (with the scaffold
    fading out across the resume); a run that stops before the fade's end says so."""
    fade = {"model.prior_fade_start": 2, "model.prior_fade_end": 5}
    train(_cfg(tiny_data, max_steps=6, **fade), tmp_path / "straight", progress=False)
    with pytest.warns(UserWarning, match="before the slot-prior scaffold was faded out"):
        train(_cfg(tiny_data, max_steps=3, **fade), tmp_path / "split", progress=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train(_cfg(tiny_data, max_steps=6, **fade), tmp_path / "split", resume=True, progress=False)
    assert not [w for w in caught if "keeps its configuration" in str(w.message)]  # nothing to set aside
    weights = [json.loads(line)["prior_weight"] for line in (tmp_path / "split/metrics.jsonl").open()]
    assert weights == pytest.approx([1, 1, 1, 2 / 3, 1 / 3, 0])
    a, b = _weights(tmp_path / "straight"), _weights(tmp_path / "split")
    assert load_checkpoint(tmp_path / "split")["step"] == 6
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


def test_a_training_checkpoint_of_the_one_class_pose_network_resumes_exactly(tiny_data, tmp_path):
    """A training checkpoint in the layout of the pose network before its parts (keys ``encoder.N.0.*``,
    ``pose_pred.*``, the scaffold's ``slot_prior`` inside the network) resumes to the weights of a run in one
    go: the keys map, the prior moves to the scaffold, the optimiser's moments stay with their parameters
    (the parameters keep their order), and the panoramas' extent recorded in the configuration becomes
    run metadata."""
    import re

    fade = {"model.prior_fade_start": 2, "model.prior_fade_end": 5}
    train(_cfg(tiny_data, max_steps=5, **fade), tmp_path / "straight", progress=False)
    with pytest.warns(UserWarning, match="faded out"):
        train(_cfg(tiny_data, max_steps=3, **fade), tmp_path / "old", progress=False)
    ckpt = tmp_path / "old" / "checkpoints" / "latest.pt"
    state = load_checkpoint(ckpt)
    old = {}
    for key, value in state["pose_net"].items():
        key = re.sub(r"^net\.pair\.encoder\.convs\.(\d+)\.", r"encoder.\1.0.", key)
        old[key.replace("net.pair.head.conv.", "pose_pred.")] = value
    old["slot_prior"] = state.pop("scaffold")["slot_prior"]
    state["config"]["data"]["vfov_h"] = state.pop("dataset")["vfov_h"]  # recorded there then
    assert "pose_pred.weight" in old and "encoder.6.0.bias" in old
    state["pose_net"] = old
    del state["path"], state["format"]
    save_checkpoint(ckpt, state)
    train(_cfg(tiny_data, max_steps=5, **fade), tmp_path / "old", resume=True, progress=False)
    resumed = load_checkpoint(tmp_path / "old")
    assert resumed["dataset"] == {"vfov_h": 1.0} and "vfov_h" not in resumed["config"]["data"]
    a, b = _weights(tmp_path / "straight"), _weights(tmp_path / "old")
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(tiny_data, tmp_path, monkeypatch):
    run = tmp_path / "run"
    train(_cfg(tiny_data, max_steps=2), run, progress=False)
    good = _weights(run)
    trainer = Trainer(_cfg(tiny_data, max_steps=4), run, resume=True)
    original = trainer.compute_loss

    def poisoned(batch):
        total, terms, visuals = original(batch)
        return total * float("nan"), terms, visuals

    monkeypatch.setattr(trainer, "compute_loss", poisoned)
    with pytest.raises(NonFiniteLossError, match="non-finite loss at step 3"):
        trainer.fit(progress=False)
    trainer.close()
    after = _weights(run)
    for k in good:
        torch.testing.assert_close(good[k], after[k], rtol=0, atol=0)


def test_checkpoints_are_untrusted_input(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=str(bad)):
        load_checkpoint(bad)
    save_checkpoint(tmp_path / "partial.pt", {"step": 1})
    with pytest.raises(CheckpointError, match="missing"):
        load_checkpoint(tmp_path / "partial.pt")

    # a pickle that would run code is refused by weights_only loading
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    torch.save({"format": "cylsfm-checkpoint-v1", "x": Evil()}, tmp_path / "evil.pt")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "evil.pt")
    with pytest.raises(CheckpointError, match="without checkpoints"):
        load_checkpoint(tmp_path)


def test_cli_train_and_bad_size(tiny_data, tmp_path, capsys):
    args = [
        "train",
        "--data",
        str(tiny_data),
        "--out",
        str(tmp_path / "r"),
        "--size",
        "128x32",
        "--split",
        "all",
    ]
    assert (
        main([*args, "--max-steps", "2", "--workers", "0", "--no-progress", "batch_size=2", "log_every=1"])
        == 0
    )
    assert [r["step"] for r in _metrics(tmp_path / "r")] == [1, 2]
    models = load_models(tmp_path / "r")
    cfg = models.config
    assert models.step == 2 and (cfg.data.width, cfg.data.height, cfg.batch_size) == (128, 32, 2)
    assert cfg.data.split is None and cfg.data.root == str(tiny_data)
    assert main(["train", "--data", str(tiny_data), "--out", str(tmp_path / "r2"), "--size", "120x32"]) == 2
    assert "multiple of 128" in capsys.readouterr().err
    assert main(["train", "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "r3")]) == 2


def test_fov_crop_trains_on_the_cropped_width(tiny_data, tmp_path):
    """``--fov 180`` of 256-pixel panoramas: the networks see the centred 128 columns, without wrap-around."""
    run = tmp_path / "crop"
    args = ["train", "--data", str(tiny_data), "--out", str(run), "--size", "256x32", "--fov", "180"]
    args += ["--split", "all", "--max-steps", "1", "--workers", "0", "--no-progress", "batch_size=2"]
    assert main([*args, "image_every=1"]) == 0
    [row] = _metrics(run)
    assert row["step"] == 1
    [image] = _tensorboard(run).Images("target")  # what the networks were given
    assert (image.width, image.height) == (128, 32)
    models = load_models(run)
    cfg = models.config
    assert (cfg.data.fov, cfg.data.width, cfg.wrap) == (180, 256, False)
    assert models.disp_net.wrap is False and models.pose_net.net.wrap is False
    # a 256-pixel panorama given to the trained model is cropped to those 128 columns
    predictor = Predictor(models)
    camera = CylindricalCamera.full(256, 32)
    assert predictor.window(camera) == (64, 192)
    assert predictor.network_camera(camera).width == 128
    images = torch.rand(1, 3, 32, 256)
    assert predictor.disparity(images, camera).shape == (1, 1, 32, 128)
    assert predictor.depth(images, camera).shape == (1, 1, 32, 128)


def test_equivariant_head_is_trained_and_restored(tiny_data, tmp_path):
    """The yaw-equivariant pose head: the restored network turns its output with a roll of the panoramas (the
    averaging head would be invariant to it)."""
    run = tmp_path / "eq"
    extra = {
        "model.pose_head": "equivariant",
        "data.width": 256,
        "model.compass": "false",
        "model.antisymmetric": "false",  # a one-source-set network: its first step already moves
    }
    assert train(_cfg(tiny_data, max_steps=1, **extra), run, progress=False)["steps"] == 1
    [row] = _metrics(run)
    assert row["step"] == 1 and row["translation_norm"] > 0
    models = load_models(run)
    assert models.config.model.pose_head == "equivariant"
    assert type(models.pose_net.net.head).__name__ == "EquivariantPoseHead"
    gen = torch.Generator().manual_seed(0)
    target, sources = torch.rand(1, 3, 32, 256, generator=gen), torch.rand(1, 2, 3, 32, 256, generator=gen)
    with torch.no_grad():
        pose, _ = models.pose_net(target, sources)
        rolled, _ = models.pose_net(target.roll(128, -1), sources.roll(128, -1))
    # half a turn of yaw: x and z of the translation and of the rotation vector change sign
    flip = torch.tensor([-1.0, 1.0, -1.0, -1.0, 1.0, -1.0])
    torch.testing.assert_close(rolled, pose * flip, rtol=1e-4, atol=1e-7)
    assert pose[..., [0, 2, 3, 5]].abs().max() > 1e-5  # not trivially zero


EACH_RANK_RECORDS = """
import json, os, sys
import torch
from cylsfm.train import sampler, trainer

rank, record = os.environ["RANK"], os.environ["RANK_RECORD"]
read = []
_getitem = sampler.SeededDataset.__getitem__
def getitem(self, key):
    read.append(int(key[0]))
    return _getitem(self, key)
sampler.SeededDataset.__getitem__ = getitem
_fit = trainer.Trainer.fit
def fit(self, *args, **kwargs):
    summary = _fit(self, *args, **kwargs)
    weights = dict(self.model.disp_net.state_dict())
    weights.update({"pose." + k: v for k, v in self.model.pose_net.state_dict().items()})
    torch.save(weights, f"{record}/weights_{rank}.pt")
    with open(f"{record}/rank_{rank}.json", "w") as f:
        json.dump({"read": read, "steps": summary["steps"], "stopped": summary["stopped"],
                   "seconds": summary["seconds"]}, f)
    return summary
trainer.Trainer.fit = fit
from cylsfm.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_data_parallel_with_two_cpu_processes(tiny_data, tmp_path):
    """torchrun with 2 gloo processes: the ranks read different samples, yet their weights stay the same
    after the steps (the gradients are averaged), and rank 0 writes one checkpoint of those weights."""
    script, record = tmp_path / "recording.py", tmp_path / "record"
    script.write_text(EACH_RANK_RECORDS)
    record.mkdir()
    run = tmp_path / "ddp"
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
        str(script), "train", "--data", str(tiny_data), "--out", str(run), "--size", "128x32",
        "--split", "all", "--max-steps", "2", "--workers", "0", "--no-progress", "--device", "cpu",
        "batch_size=2", "latest_every=1", "log_every=1",
    ]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1", RANK_RECORD=str(record), PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert load_checkpoint(run)["step"] == 2
    assert [r["step"] for r in _metrics(run)] == [1, 2]  # logged once, by rank 0
    ranks = [json.loads((record / f"rank_{r}.json").read_text()) for r in (0, 1)]
    assert [r["steps"] for r in ranks] == [2, 2]
    reads = [r["read"][:4] for r in ranks]  # two steps of two samples each
    assert all(len(r) == 4 for r in reads), reads
    assert not set(reads[0]) & set(reads[1]), (
        f"both processes read the samples {set(reads[0]) & set(reads[1])}"
    )
    weights = [torch.load(record / f"weights_{r}.pt") for r in (0, 1)]
    differ = [k for k in weights[0] if not torch.equal(weights[0][k], weights[1][k])]
    assert not differ, f"the processes' weights drifted apart (gradients not averaged): {differ[:3]}"
    saved = _weights(run)
    assert saved.keys() == weights[0].keys()
    assert all(torch.equal(saved[k], weights[0][k]) for k in saved)  # the checkpoint: those weights


def test_the_compass_is_trained_and_restored(tiny_data, tmp_path):
    """model.compass with the one-pass network: the total is the sum of the logged terms, and the restored
    pose model adds the compass's yaw to its network's pose."""
    from cylsfm.geometry import roll_angle

    run = tmp_path / "compass"
    extra = {"model.compass": "true", "model.antisymmetric": "false", "data.width": 256}
    assert train(_cfg(tiny_data, max_steps=2, **extra), run, progress=False)["steps"] == 2
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2
    for row in rows:
        assert math.isfinite(row["total"])
        assert row["total"] == pytest.approx(row["photometric"] + row["smooth"] + row["explain"], rel=1e-6)
    models = load_models(run)
    assert models.config.model.compass and models.pose_net.compass is not None
    gen = torch.Generator().manual_seed(0)
    target = torch.nn.functional.avg_pool2d(torch.rand(1, 3, 32, 256, generator=gen), 3, 1, 1)
    sources = torch.stack((target, target.roll(16, -1)), 1)
    with torch.no_grad():
        with_compass, _ = models.pose_net(target, sources)
        without, _ = models.pose_net.net(target, sources)
    expected = torch.zeros(1, 2, 6)
    expected[0, 1, 4] = roll_angle(16, 256)
    torch.testing.assert_close(with_compass - without, expected, rtol=1e-5, atol=1e-6)


def test_compass_and_pose_settings_are_checked():
    from cylsfm.model import build_models
    from cylsfm.model.config import ConfigError

    crop = apply_overrides(preset("default"), ["model.compass=true", "data.fov=180"])
    assert build_models(crop)[1].compass is None  # a crop is no full panorama: no compass
    assert type(build_models(crop)[1].net.pair.head).__name__ == "MeanPoseHead"  # "auto": no full circle
    assert type(build_models(preset("default"))[1].net.pair.head).__name__ == "EquivariantPoseHead"
    with pytest.raises(ConfigError, match="equivariant needs full 360-degree"):
        apply_overrides(preset("default"), ["model.pose_head=equivariant", "data.fov=180"])
    with pytest.raises(ConfigError, match="antisymmetric"):
        apply_overrides(preset("default"), ["model.antisymmetric=true", "model.explainability=true"])


def test_slot_prior_scaffold_is_built_for_the_pair_network_only(tiny_data, tmp_path):
    from cylsfm.model import build_models
    from cylsfm.model.config import ConfigError

    cfg = apply_overrides(
        preset("improved"),
        ["model.antisymmetric=true", "model.prior_fade_start=10", "model.prior_fade_end=30"],
    )
    assert cfg.model.scaffold
    assert not apply_overrides(preset("default"), ["model.antisymmetric=false"]).model.scaffold
    assert not apply_overrides(preset("default"), ["model.prior_fade_end=0"]).model.scaffold
    assert "slot_prior" not in str(list(build_models(cfg)[1].state_dict()))  # never in the inference model
    trainer = Trainer(_cfg(tiny_data, max_steps=1), tmp_path / "run")
    assert trainer.scaffold is not None and trainer.scaffold.fade_end == trainer.cfg.model.prior_fade_end
    assert (
        Trainer(_cfg(tiny_data, max_steps=1, **{"model.prior_fade_end": 0}), tmp_path / "b").scaffold is None
    )
    with pytest.raises(ConfigError, match="start <= end"):
        apply_overrides(
            preset("default"),
            ["model.antisymmetric=true", "model.prior_fade_start=40", "model.prior_fade_end=30"],
        )


def test_saved_configurations_keep_the_settings_they_were_written_with():
    """A run's saved configuration that predates a field gets the field's default (the setting off), not
    today's preset: an old default-recipe checkpoint rebuilds the pose network it trained."""
    from cylsfm.model import build_models, config_from_dict, config_to_dict

    old = config_to_dict(preset("improved"))
    old["preset"] = "default"
    for key in ("compass", "antisymmetric", "prior_fade_start", "prior_fade_end", "prior_distill"):
        del old["model"][key]
    saved = config_from_dict(old, "old run", saved=True)
    assert not saved.model.compass and not saved.model.antisymmetric and not saved.model.scaffold
    assert saved.pose_head == "mean" and build_models(saved)[1].net.encoder.convs[0].in_channels == 9
    assert config_from_dict(old, "a user's file").model.antisymmetric  # user files start from the preset
