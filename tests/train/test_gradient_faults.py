"""Non-finite gradients: fp16 training skips the step (the gradient scaler's job) and goes on; fp32 stops
before the optimiser writes them into the weights. fp16 autocast is a CUDA feature here; the same code runs
on the CPU (autocast and the gradient scaler both exist there), so it is tested on the CPU."""

import pytest
import torch

from cylsfm.train import trainer as trainer_module
from cylsfm.train.trainer import NonFiniteLossError, Trainer
from helpers import tiny_training_config


def _cfg(root, **extra):
    return tiny_training_config(root, image_every=0, device="cpu", **extra)


def _poison_gradients(trainer, steps):
    """Make the gradient of one weight infinite in the backward pass of each step (1-based) in ``steps``."""
    weight = next(trainer.model.disp_net.parameters())
    weight.register_hook(lambda g: g * float("inf") if trainer.step + 1 in steps else g)


def _weights(trainer):
    return [p.detach().clone() for p in trainer.model.parameters()]


def _fp16(monkeypatch):
    monkeypatch.setattr(trainer_module, "autocast_dtype", lambda device, amp: torch.float16)


def test_fp16_skips_a_step_whose_gradients_overflow_and_goes_on(tiny_data, tmp_path, monkeypatch):
    _fp16(monkeypatch)
    trainer = Trainer(_cfg(tiny_data, max_steps=12), tmp_path / "run")
    assert trainer.scaler.is_enabled() and trainer.amp_dtype == torch.float16
    # The scaler starts high and skips steps until its scale fits; once a step has updated the weights,
    # the next one's gradients are made infinite.
    plan = {"armed": False, "poisoned": None}

    def poison(g):
        if plan["armed"] and plan["poisoned"] is None:
            plan["poisoned"] = trainer.step + 1
            return g * float("inf")
        return g

    next(trainer.model.disp_net.parameters()).register_hook(poison)
    seen = []
    step = trainer.train_step

    def recording(batch):
        before, scale = _weights(trainer), trainer.scaler.get_scale()
        scalars, visuals = step(batch)
        updated = not all(torch.equal(a, b) for a, b in zip(before, _weights(trainer), strict=True))
        plan["armed"] = plan["armed"] or updated
        seen.append({"updated": updated, "scale": scale, **scalars})
        return scalars, visuals

    monkeypatch.setattr(trainer, "train_step", recording)
    summary = trainer.fit(progress=False)
    trainer.close()
    assert summary["steps"] == 12 and summary["stopped"] == "max_steps"
    k = plan["poisoned"]
    assert k is not None and seen[k - 2]["updated"], "no step updated the weights before the poisoned one"
    poisoned, after = seen[k - 1], seen[k:]
    assert not poisoned["updated"] and poisoned["grad_norm"] == float("inf")
    assert poisoned["skipped_steps"] == seen[k - 2]["skipped_steps"] + 1
    assert after and after[0]["scale"] == poisoned["scale"] / 2  # the scaler halved its scale
    assert any(s["updated"] for s in after)  # and training went on
    for s in seen:  # a step is skipped exactly when its gradients were not finite
        assert s["updated"] == (s["grad_norm"] < float("inf"))
    skipped = sum(not s["updated"] for s in seen)
    assert seen[-1]["skipped_steps"] == skipped
    assert torch.load(tmp_path / "run/checkpoints/latest.pt", weights_only=True)["skipped_steps"] == skipped


def test_fp16_stops_after_too_many_overflows_in_a_row(tiny_data, tmp_path, monkeypatch):
    _fp16(monkeypatch)
    monkeypatch.setattr(trainer_module, "_MAX_SKIPPED_IN_A_ROW", 3)
    trainer = Trainer(_cfg(tiny_data, max_steps=8), tmp_path / "run")
    _poison_gradients(trainer, set(range(1, 9)))
    with pytest.raises(NonFiniteLossError, match="3 fp16 steps in a row at step 3"):
        trainer.fit(progress=False)
    trainer.close()


def test_fp32_stops_on_a_non_finite_gradient_before_the_weights_change(tiny_data, tmp_path):
    trainer = Trainer(_cfg(tiny_data, max_steps=4), tmp_path / "run")
    assert not trainer.scaler.is_enabled()
    _poison_gradients(trainer, {3})
    with pytest.raises(NonFiniteLossError, match=r"non-finite gradients \(norm inf\) in a step at step 3"):
        trainer.fit(progress=False)
    weights = _weights(trainer)
    trainer.close()
    assert trainer.step == 2 and all(torch.isfinite(w).all() for w in weights)
    saved = torch.load(tmp_path / "run/checkpoints/latest.pt", weights_only=True)
    assert saved["step"] == 2  # the last good checkpoint
    mine = dict(trainer.model.disp_net.state_dict())
    for k, v in saved["disp_net"].items():
        assert torch.equal(v, mine[k]), k  # the weights in memory are still the good step's


def test_the_gradient_norm_is_logged(tiny_data, tmp_path):
    trainer = Trainer(_cfg(tiny_data, max_steps=1), tmp_path / "run")
    batch = next(iter(trainer._loader()))
    scalars, _ = trainer.train_step(batch)
    trainer.close()
    grads = [p.grad for p in trainer.model.parameters() if p.grad is not None]
    expected = torch.linalg.vector_norm(torch.cat([g.flatten() for g in grads]))
    assert scalars["grad_norm"] == pytest.approx(float(expected), rel=1e-5)
    assert "skipped_steps" not in scalars  # fp32: nothing is ever skipped
