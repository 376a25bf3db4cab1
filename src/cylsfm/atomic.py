"""Atomic file writes: a temporary file in the same directory, then ``os.replace``.

Readers never see a partly written file, and an interrupted write leaves the previous file intact. The
file gets the permissions a plain ``open`` would give it (``0o666`` less the process's umask), not the
private ``0o600`` of a temporary file: outputs are meant to be shared and served (a viewer's folder).
Checkpoints, prepared data, split files, trajectories and reports are all written through here.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from .errors import CylsfmError

__all__ = ["atomic_open", "atomic_write_bytes", "atomic_write_text"]


def _read_umask() -> int:
    mask = os.umask(0o022)  # (reading the umask means setting it: done once, at import)
    os.umask(mask)
    return mask


_MODE = 0o666 & ~_read_umask()


@contextmanager
def atomic_open(path: str | os.PathLike[str]) -> Iterator[IO[bytes]]:
    """A binary file handle whose content replaces ``path`` only when the block ends without error.

    The parent directory is created when missing. On an exception the temporary file is removed and
    ``path`` keeps its previous content; a file-system error (a full disk, a read-only directory) becomes
    a :class:`~cylsfm.errors.CylsfmError` naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            os.fchmod(fh.fileno(), _MODE)
            yield fh
        os.replace(tmp, path)
    except OSError as exc:  # a full disk, a read-only or vanished directory: one line, the old file kept
        Path(tmp).unlink(missing_ok=True)
        raise _cannot_write(path, exc) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _cannot_write(path: Path, exc: OSError) -> CylsfmError:
    reason = exc.strerror or str(exc) or type(exc).__name__
    return CylsfmError(f"{path}: cannot write ({reason}); a previous {path.name} is kept as it was")


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically; the parent directory is created when missing."""
    with atomic_open(path) as fh:
        fh.write(data)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))
