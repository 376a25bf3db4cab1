import os
import subprocess
import sys

import pytest
import torch

from cylsfm.cli import main
from cylsfm.model import CheckpointError, load_checkpoint, load_models, save_checkpoint
from cylsfm.model.config import apply_overrides, preset
from cylsfm.train.trainer import NonFiniteLossError, Trainer, train


def _cfg(root, **extra):
    items = [
        f"data.root='{root}'",
        "data.width=128",
        "data.height=32",
        "data.split=null",
        "data.workers=0",
        "batch_size=2",
        "log_every=1",
        "image_every=2",
        "latest_every=1",
        "checkpoint_every=0",
    ] + [f"{k}={v}" for k, v in extra.items()]
    return apply_overrides(preset("default"), items)


def _weights(run):
    state = load_checkpoint(run)
    return {k: v.clone() for k, v in state["disp_net"].items()} | {
        "pose." + k: v.clone() for k, v in state["pose_net"].items()
    }


def test_training_writes_config_logs_and_checkpoints(tiny_data, tmp_path):
    run = tmp_path / "run"
    summary = train(_cfg(tiny_data, max_steps=3), run, progress=False)
    assert summary["steps"] == 3
    assert (run / "config.yaml").exists() and (run / "metrics.jsonl").exists()
    assert any((run / "tb").iterdir())
    models = load_models(run)  # a run directory means its latest checkpoint
    assert models.step == 3 and models.config.data.width == 128


def test_resume_continues_exactly(tiny_data, tmp_path):
    """3 + 3 steps with a resume in between give the same weights as 6 steps in one go."""
    train(_cfg(tiny_data, max_steps=6), tmp_path / "straight", progress=False)
    train(_cfg(tiny_data, max_steps=3), tmp_path / "split", progress=False)
    train(_cfg(tiny_data, max_steps=6), tmp_path / "split", resume=True, progress=False)
    a, b = _weights(tmp_path / "straight"), _weights(tmp_path / "split")
    assert load_checkpoint(tmp_path / "split")["step"] == 6
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
    assert main([*args, "--max-steps", "2", "--workers", "0", "--no-progress", "batch_size=2"]) == 0
    assert main(["train", "--data", str(tiny_data), "--out", str(tmp_path / "r2"), "--size", "120x32"]) == 2
    assert "multiple of 128" in capsys.readouterr().err
    assert main(["train", "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "r3")]) == 2


def test_fov_crop_and_equivariant_head_train(tiny_data, tmp_path):
    run = train(
        _cfg(tiny_data, max_steps=1, **{"data.fov": 180, "data.width": 256}),
        tmp_path / "crop",
        progress=False,
    )
    assert run["steps"] == 1
    assert load_models(tmp_path / "crop").config.wrap is False
    eq = _cfg(tiny_data, max_steps=1, **{"model.pose_head": "equivariant", "data.roll": "true"})
    assert train(eq, tmp_path / "eq", progress=False)["steps"] == 1


def test_data_parallel_with_two_cpu_processes(tiny_data, tmp_path):
    """torchrun with 2 gloo processes: ranks share the data, rank 0 writes one checkpoint."""
    run = tmp_path / "ddp"
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", "29571",
        "-m", "cylsfm.cli", "train", "--data", str(tiny_data), "--out", str(run), "--size", "128x32",
        "--split", "all", "--max-steps", "2", "--workers", "0", "--no-progress", "--device", "cpu",
        "batch_size=2", "latest_every=1",
    ]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert load_checkpoint(run)["step"] == 2


def test_plain_photometric_warm_up_is_used_by_the_trainer(tiny_data, tmp_path):
    """During the warm-up the trainer's loss is the plain one; after it, the configured one."""
    trainer = Trainer(_cfg(tiny_data, max_steps=1, plain_photometric_steps=1), tmp_path / "run")
    batch = next(iter(trainer._loader()))
    plain_items = ["loss.ssim_weight=0", "loss.min_reprojection=false", "loss.automask=false"]
    plain = Trainer(
        apply_overrides(_cfg(tiny_data), [*plain_items, "loss.full_resolution=false"]), tmp_path / "plain"
    )
    plain.model.load_state_dict(trainer.model.state_dict())
    warm, _, _ = trainer.compute_loss(batch)
    ref, _, _ = plain.compute_loss(batch)
    trainer.step = 1
    after, _, _ = trainer.compute_loss(batch)
    torch.testing.assert_close(warm, ref)
    assert not torch.allclose(warm, after)
