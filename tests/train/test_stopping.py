"""When training stops: every process of a data-parallel run at the same step, a scheduler's SIGTERM like
Ctrl-C (a checkpoint, a resume that continues), and no run overwritten by accident."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from cylsfm.cli import main
from cylsfm.model import load_checkpoint

ARGS = ["--size", "128x32", "--split", "all", "--workers", "0", "--no-progress", "--device", "cpu"]
ARGS += ["batch_size=2", "log_every=1", "latest_every=1000", "checkpoint_every=0"]


def _steps(run: Path) -> list[int]:
    return [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_an_existing_run_is_refused_without_resume_and_started_over_with_overwrite(
    tiny_data, tmp_path, capsys
):
    run = tmp_path / "run"
    base = ["train", "--data", str(tiny_data), "--out", str(run), *ARGS]
    assert main([*base, "--max-steps", "2"]) == 0
    before = (run / "checkpoints" / "latest.pt").read_bytes()
    capsys.readouterr()
    assert main([*base, "--max-steps", "1"]) == 2  # no silent restart from step 0
    err = capsys.readouterr().err
    assert str(run) in err and "--resume" in err and "--overwrite" in err and err.count("\n") == 1
    assert (run / "checkpoints" / "latest.pt").read_bytes() == before and _steps(run) == [1, 2]
    assert main([*base, "--max-steps", "1", "--overwrite"]) == 0
    assert "removed checkpoints, metrics.jsonl" in capsys.readouterr().err
    assert load_checkpoint(run)["step"] == 1 and _steps(run) == [1]  # started again, the old log gone
    assert main([*base, "--resume", "--overwrite"]) == 2


def test_sigterm_saves_a_checkpoint_and_the_run_resumes(tiny_data, tmp_path):
    """A scheduler's SIGTERM mid-run: the step in progress ends, a checkpoint at that step is written, the
    command says so and exits; --resume continues from it."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "cylsfm.cli", "train", "--data", str(tiny_data), "--out", str(run), *ARGS]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen([*cmd, "--max-steps", "100000"], env=env, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not ((run / "metrics.jsonl").exists() and len(_steps(run)) >= 3):
            assert proc.poll() is None and time.monotonic() < deadline, "training did not start"
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err[-2000:]
    assert "stopped by SIGTERM" in err and "--resume" in err
    step = load_checkpoint(run)["step"]
    assert step == _steps(run)[-1] >= 3  # the checkpoint is the last step done
    out = subprocess.run(
        [*cmd, "--resume", "--max-steps", str(step + 2)], env=env, capture_output=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert load_checkpoint(run)["step"] == step + 2 and _steps(run)[-2:] == [step + 1, step + 2]


SKEWED = """
import json, os, sys, time
rank = os.environ["RANK"]
if rank == "1":  # this process's clock runs four times as fast: its budget ends first
    _monotonic = time.monotonic
    time.monotonic = lambda: 4.0 * _monotonic()
from cylsfm.train import trainer
_fit = trainer.Trainer.fit
def fit(self, *args, **kwargs):  # each process writes down where and why it stopped
    summary = _fit(self, *args, **kwargs)
    with open(os.path.join(os.environ["RANK_RECORD"], f"rank_{rank}.json"), "w") as f:
        json.dump(summary, f)
    return summary
trainer.Trainer.fit = fit
from cylsfm.cli import main
sys.exit(main(sys.argv[1:]))
"""

BUDGET_S = 12.0


def test_data_parallel_processes_agree_when_the_budget_ends(tiny_data, tmp_path):
    """torchrun, 2 gloo processes, one with a clock running four times as fast, and a budget of 12 s: that
    one's budget ends after about 3 s, and the other process stops with it, at the same step, long before
    its own budget ends (each process writes down its step, its reason and its seconds by its own clock);
    rank 0 writes one checkpoint there. Without the agreement the process whose budget ends first leaves
    while the other waits in a gradient all-reduce; with an agreement that waited for every process's
    budget, both would run the full 12 s."""
    script, record = tmp_path / "skewed.py", tmp_path / "record"
    script.write_text(SKEWED)
    record.mkdir()
    run = tmp_path / "ddp"
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
        str(script), "train", "--data", str(tiny_data), "--out", str(run), *ARGS,
        "--max-steps", "100000", "--minutes", str(BUDGET_S / 60),
    ]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1", RANK_RECORD=str(record), PYTHONPATH=os.pathsep.join(sys.path))
    start = time.monotonic()
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    steps = _steps(run)
    assert 0 < steps[-1] < 100000 and load_checkpoint(run)["step"] == steps[-1]
    assert time.monotonic() - start < 150
    ranks = [json.loads((record / f"rank_{r}.json").read_text()) for r in (0, 1)]
    assert [r["steps"] for r in ranks] == [steps[-1]] * 2, ranks
    assert [r["stopped"] for r in ranks] == ["minutes"] * 2, ranks
    assert ranks[1]["seconds"] >= BUDGET_S, ranks  # the fast clock's budget ended...
    assert ranks[0]["seconds"] < 0.75 * BUDGET_S, ranks  # ... and the other process stopped with it


NAN_ON_RANK_1 = """
import os, sys
if os.environ.get("RANK") == "1":  # this process's loss becomes NaN at its third step
    from cylsfm.train import objective
    _call, _n = objective.Objective.__call__, [0]

    def nan_at_three(self, batch, outputs):
        total, terms, visuals = _call(self, batch, outputs)
        _n[0] += 1
        return (total * float("nan") if _n[0] == 3 else total), terms, visuals

    objective.Objective.__call__ = nan_at_three
from cylsfm.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_non_finite_loss_in_one_process_stops_them_all(tiny_data, tmp_path):
    """torchrun, 2 gloo processes, a NaN loss in the second only: both stop with the message (no process
    waits for the other in a gradient all-reduce) and the last good checkpoint is kept."""
    script = tmp_path / "nan.py"
    script.write_text(NAN_ON_RANK_1)
    run = tmp_path / "ddp"
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
        str(script), "train", "--data", str(tiny_data), "--out", str(run), "--max-steps", "100",
        *(a.replace("latest_every=1000", "latest_every=1") for a in ARGS),
    ]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    assert out.returncode != 0
    assert "non-finite loss at step 3" in out.stderr and "in another process" in out.stderr
    assert load_checkpoint(run)["step"] == 2
