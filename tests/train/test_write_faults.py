"""Writes that fail (a full disk, a read-only directory) leave the previous file intact and stop with one
line naming the path: the atomic writer, and the training command whose checkpoint it writes."""

from __future__ import annotations

import errno
import os

import pytest
import torch

from cylsfm.atomic import atomic_write_text
from cylsfm.cli import main
from cylsfm.errors import CylsfmError
from helpers import failing_writes


def test_a_full_disk_keeps_the_previous_file_and_names_it(tmp_path, monkeypatch):
    path = tmp_path / "report.md"
    atomic_write_text(path, "the old report\n")
    failing_writes(monkeypatch, "report.md", errno.ENOSPC)
    with pytest.raises(CylsfmError, match=r"report\.md: cannot write \(No space left on device\)") as info:
        atomic_write_text(path, "the new report\n")
    assert "\n" not in str(info.value)
    assert path.read_text() == "the old report\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.md"]  # no temporary file left behind


def test_a_read_only_directory_is_one_line(tmp_path, monkeypatch):
    failing_writes(monkeypatch, "out.json", errno.EROFS)
    with pytest.raises(CylsfmError, match=r"out\.json: cannot write \(Read-only file system\)"):
        atomic_write_text(tmp_path / "out.json", "{}")


def test_train_stops_on_a_full_disk_with_the_last_checkpoint_intact(tiny_data, tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    args = ["train", "--data", str(tiny_data), "--out", str(run), "--size", "128x32", "--split", "all"]
    args += ["--workers", "0", "--no-progress", "--device", "cpu", "batch_size=2"]
    assert main([*args, "--max-steps", "1"]) == 0
    before = (run / "checkpoints" / "latest.pt").read_bytes()

    def full(obj, f, *a, **kw):
        f.write(b"partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(torch, "save", full)
    capsys.readouterr()
    assert main([*args, "--resume", "--max-steps", "2"]) == 2
    err = capsys.readouterr().err
    assert "latest.pt: cannot write (No space left on device)" in err and err.count("\n") == 1
    assert (run / "checkpoints" / "latest.pt").read_bytes() == before
