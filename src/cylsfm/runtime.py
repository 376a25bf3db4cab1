"""Where and how jobs run: the device choice, the precision the networks run in, and the one progress-bar
factory every job uses."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch

from .errors import CylsfmError

__all__ = [
    "autocast_dtype",
    "file_id",
    "fingerprint",
    "native_bf16",
    "network_precision",
    "pick_device",
    "prefers_channels_last",
    "progress_bar",
]


def pick_device(name: str = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else the CPU; otherwise ``torch.device(name)``.

    Raises:
        CylsfmError: a CUDA device was asked for on a machine without CUDA, or the name is not a device.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise CylsfmError(f"unknown device {name!r} (auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CylsfmError(f"device {name!r} requested but CUDA is not available")
    return dev


def prefers_channels_last(device: torch.device) -> bool:
    """Whether training convolutions run faster in channels-last memory on ``device``.

    Measured on the CPU (BENCHMARKS.md, a 512x128 training step): with AVX-512 channels-last is faster
    (0.75 s against 0.86 s); with AVX2 only it is slower (2.22 s against 1.64 s; 1.27-1.64x at 256x64).
    On CUDA it is chosen because cuDNN's tensor-core convolutions expect that layout; it has not been
    measured there.
    """
    if device.type != "cpu":
        return device.type == "cuda"
    return torch.backends.cpu.get_cpu_capability().upper().startswith(("AVX512", "AMX"))


@functools.cache
def native_bf16() -> bool:
    """Whether this CPU computes bf16 in hardware (AVX-512 BF16 or AMX tiles).

    There oneDNN's bf16 convolutions run 1.3-3.6x faster than fp32 (BENCHMARKS.md, "bf16 on the CPU"); on
    other CPUs bf16 is emulated and slower than fp32, so they keep fp32.
    """
    cpu = getattr(torch, "cpu", None)
    try:
        return bool(cpu._is_avx512_bf16_supported() or cpu._is_amx_tile_supported())  # type: ignore[union-attr]
    except (AttributeError, RuntimeError):  # an older or newer torch without these: read the CPU's flags
        try:
            flags = Path("/proc/cpuinfo").read_text().split()
        except OSError:
            return False
        return "avx512_bf16" in flags or "amx_bf16" in flags


def autocast_dtype(device: torch.device, amp: bool) -> torch.dtype | None:
    """The dtype the networks run in under ``amp`` on ``device`` (``None``: fp32).

    CUDA: bf16 where the GPU has it, else fp16 (whose overflowing training steps the gradient scaler skips).
    CPU: bf16 where it is native (:func:`native_bf16`), else fp32. Losses, the sampler and the geometry
    stay in fp32 in any case (they cast the networks' outputs, or run with autocast off).
    """
    if not amp:
        return None
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    if device.type == "cpu" and native_bf16():
        return torch.bfloat16
    return None


def network_precision(device: torch.device, dtype: torch.dtype | None) -> contextlib.AbstractContextManager:
    """The context the networks run in: autocast to ``dtype`` on ``device`` (from :func:`autocast_dtype`),
    or nothing for fp32."""
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=dtype)


def progress_bar(
    iterable: Iterable[Any] | None = None,
    *,
    total: float | None = None,
    desc: str | None = None,
    unit: str = "it",
    enabled: bool | None = True,
    leave: bool = False,
) -> Any:
    """A tqdm progress bar on stderr, the same look in every job.

    Args:
        iterable: wrap this iterable (or ``None`` and call ``update`` by hand).
        total: the expected count (frames, steps, seconds).
        desc: the label in front of the bar.
        unit: what is counted.
        enabled: ``True`` shows it, ``False`` hides it, ``None`` shows it only on a terminal.
        leave: keep the finished bar on screen.

    Returns:
        A ``tqdm`` object (also when hidden: ``update``, ``set_postfix`` and ``close`` then do nothing).
    """
    from tqdm import tqdm

    return tqdm(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        disable=None if enabled is None else not enabled,
        leave=leave,
        dynamic_ncols=True,
        file=sys.stderr,
    )


def file_id(path: Path) -> str:
    """A file's resolved path, size and modification time (what a resumed result was computed from)."""
    p = Path(path).resolve()
    stat = p.stat() if p.exists() else None
    return f"{p} {stat.st_size if stat else 0} {stat.st_mtime_ns if stat else 0}"


def fingerprint(settings: dict[str, Any]) -> str:
    """A short digest of the settings that determine a result (JSON-able values): a saved run or a prepared
    sequence with another fingerprint is not continued."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:24]
