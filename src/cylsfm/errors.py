"""The project's error type, its shape guard, and the one place where file-system errors become it.

Every problem a user can cause (a missing or corrupt file, a wrong size, an invalid option or argument) is
a :class:`CylsfmError`: the command line reports it in one line that names the file and the problem. The
subclasses that stand for invalid *values* also derive from ``ValueError``, so library callers may catch
either.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["CylsfmError", "InputError", "ShapeError", "check_shape", "reading"]


class CylsfmError(Exception):
    """A problem with input the user gave (a file, a flag); the message names the file and the problem."""


class InputError(CylsfmError, ValueError):
    """An invalid argument or option value."""


class ShapeError(InputError):
    """A tensor of the wrong shape."""


def check_shape(x: object, shape: str, name: str = "input") -> None:
    """Raise :class:`ShapeError` unless ``x`` is a tensor (or array) of the given shape.

    ``shape`` is a comma-separated pattern: a number must match exactly, a name matches any size
    (``"B,3,H,W"``), and a leading ``*`` allows any number of extra leading dimensions (``"*,4,4"``).

    >>> import torch
    >>> check_shape(torch.zeros(2, 1, 8, 16), "B,1,H,W", "depth")
    >>> check_shape(torch.zeros(2, 3, 8, 16), "B,1,H,W", "depth")
    Traceback (most recent call last):
    ...
    cylsfm.errors.ShapeError: depth must be [B,1,H,W], got (2, 3, 8, 16)
    """
    dims = [d.strip() for d in shape.split(",")]
    size = tuple(getattr(x, "shape", ()))
    ok = hasattr(x, "shape")
    if ok and dims and dims[0] == "*":
        dims = dims[1:]
        ok = len(size) >= len(dims)
        size_tail = size[len(size) - len(dims) :]
    else:
        ok = ok and len(size) == len(dims)
        size_tail = size
    if ok:
        ok = all(not d.isdigit() or int(d) == n for d, n in zip(dims, size_tail, strict=True))
    if not ok:
        raise ShapeError(f"{name} must be [{shape}], got {size if hasattr(x, 'shape') else type(x).__name__}")


@contextmanager
def reading(path: str | os.PathLike[str], error: type[CylsfmError] = CylsfmError) -> Iterator[None]:
    """Turn file-system and text-decoding errors while reading ``path`` into ``error`` naming the file.

    >>> with reading("no/such/file.txt"):
    ...     open("no/such/file.txt").read()
    Traceback (most recent call last):
    ...
    cylsfm.errors.CylsfmError: no/such/file.txt: not found
    """
    try:
        yield
    except FileNotFoundError:
        raise error(f"{path}: not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise error(f"{path}: cannot read ({reason})") from None
