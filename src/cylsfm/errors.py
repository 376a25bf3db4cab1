"""Exceptions for problems with the user's input (files, options), reported without a traceback."""

from __future__ import annotations

__all__ = ["CylsfmError"]


class CylsfmError(Exception):
    """A problem with input the user gave (a file, a flag); the message names the file and the problem."""
