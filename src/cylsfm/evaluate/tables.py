"""Tables of evaluation results: fixed-width text (what ``cylsfm evaluate`` prints) and Markdown (the
tables of RESULTS.md), from the same cells.

A cell is a number (printed with four decimals), a missing value (``None``, NaN or an infinity: printed
as ``-``) or a text (printed as it is). Text rows right-align each cell in its column width.

>>> text_row("", ["abs_rel", "rmse"], 9, 8)
'          abs_rel     rmse'
>>> text_row("model", [0.12345, None], 9, 8)
'model      0.1235        -'
>>> markdown_row("model", [0.12345, None])
'| model | 0.1235 | - |'
>>> markdown_rule(2)
'|---|---|---|'
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

__all__ = ["cell", "markdown_row", "markdown_rule", "ratio", "text_row"]


def cell(value: Any, width: int = 0, digits: int = 4) -> str:
    """One cell, right-aligned in ``width`` characters (``0``: as long as it needs)."""
    if isinstance(value, str):
        return value.rjust(width)
    if value is None or (isinstance(value, numbers.Real) and not math.isfinite(value)):
        return "-".rjust(width)
    return f"{value:{width}.{digits}f}" if width else f"{value:.{digits}f}"


def text_row(label: str, cells: Sequence[Any], widths: int | Sequence[int], label_width: int) -> str:
    """A fixed-width text row: ``label`` left-aligned in ``label_width`` characters, then the cells in
    ``widths`` characters each (one width for all, or one per cell)."""
    ws = [widths] * len(cells) if isinstance(widths, int) else list(widths)
    return f"{label:{label_width}}" + "".join(cell(v, w) for v, w in zip(cells, ws, strict=True))


def markdown_row(label: str, cells: Sequence[Any]) -> str:
    """A Markdown table row ``| label | cell | ... |``."""
    return "| " + " | ".join([label, *(cell(v) for v in cells)]) + " |"


def markdown_rule(columns: int) -> str:
    """The rule under a Markdown header of a label column and ``columns`` more."""
    return "|---" * (columns + 1) + "|"


def ratio(a: Any, b: Any) -> float | None:
    """``a / b``, or ``None`` when either is missing or not finite or ``b`` is 0."""
    ok = a is not None and b is not None and math.isfinite(a) and math.isfinite(b) and b != 0
    return a / b if ok else None
