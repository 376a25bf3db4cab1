"""Convolutions at inference with their weights laid out once for oneDNN.

On the CPU, an eager ``F.conv2d`` hands oneDNN the weights in PyTorch's layout, and oneDNN lays them out
again in its blocked layout at every call. On the networks' deepest layers (weights of up to
``512 x 1024 x 3 x 3`` on maps of a few positions) that copy costs more than the arithmetic, several times
more on the smallest maps, in bf16 and in fp32 alike (BENCHMARKS.md links the measurements, layer by layer).

At inference the weights do not change, so each wrap-aware layer keeps a :class:`PackedWeights`: its
weight in oneDNN's layout, made once for each input shape and dropped when the weight changes (a new
tensor, or the same one written in place: its version counter moves), and runs oneDNN's convolution on
it directly. The kernels are oneDNN's either way, so the result is what ``F.conv2d`` /
``F.conv_transpose2d`` give, up to float rounding (tested).

The laid-out path is taken only where it computes that: CPU tensors of one dtype (fp32 or bf16, the
input's and the weight's), gradients off, autocast off, oneDNN available and enabled, weights made outside
``torch.inference_mode`` (whose tensors keep no version counter), and neither an exporter nor a compiler
tracing (:func:`cylsfm.nn.padding.standard_ops`, ``torch.compile``).
:func:`plain_convolutions` turns it off (the benchmarks' "before", the tests' reference).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

from .padding import tracing

__all__ = ["PackedWeights", "available", "plain_convolutions"]

#: Input shapes remembered per layer (each holds one copy of the layer's weight); the oldest goes first.
MAX_SHAPES = 4

_ENABLED = True


@contextmanager
def plain_convolutions() -> Iterator[None]:
    """Within this block every convolution runs as plain ``F.conv2d`` / ``F.conv_transpose2d``."""
    global _ENABLED
    previous, _ENABLED = _ENABLED, False
    try:
        yield
    finally:
        _ENABLED = previous


def _ops_available() -> bool:
    ops = torch.ops.mkldnn
    return (
        torch.backends.mkldnn.is_available()
        and hasattr(ops, "_convolution_pointwise")
        and hasattr(ops, "_convolution_transpose_pointwise")
        and hasattr(ops, "_reorder_convolution_transpose_weight")
    )


_AVAILABLE = _ops_available()
_BF16 = _AVAILABLE and bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def available(dtype: torch.dtype) -> bool:
    """Whether this torch and CPU can run convolutions of ``dtype`` on laid-out weights."""
    return _AVAILABLE and (dtype == torch.float32 or (dtype == torch.bfloat16 and _BF16))


def _usable(x: Tensor, weight: Tensor, bias: Tensor | None) -> bool:
    return (
        _ENABLED
        and _AVAILABLE
        and torch.backends.mkldnn.enabled
        and x.device.type == "cpu"
        and weight.device.type == "cpu"
        and x.dim() == 4
        and x.dtype == weight.dtype
        and (x.dtype == torch.float32 or (x.dtype == torch.bfloat16 and _BF16))
        and (bias is None or bias.dtype == weight.dtype)
        and not weight.is_inference()  # made under inference_mode: no version counter to watch
        and not torch.is_grad_enabled()
        and not torch.is_autocast_enabled("cpu")
        and not tracing()
        and not torch.jit.is_tracing()
    )


class PackedWeights:
    """One layer's weight in oneDNN's layout, for inference on the CPU.

    Held by each wrap-aware layer (:class:`~cylsfm.nn.WrapConv2d`,
    :class:`~cylsfm.nn.WrapConvTranspose2d`); nothing of it is saved with the module (``state_dict``,
    ``copy.deepcopy`` and pickling give an empty one). :meth:`conv2d` and :meth:`conv_transpose2d` return
    ``None`` where the laid-out path does not apply (see the module docstring); the caller then runs its
    ordinary convolution.
    """

    def __init__(self) -> None:
        self.clear()

    def __deepcopy__(self, memo: dict) -> PackedWeights:
        return PackedWeights()

    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self.clear()

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        """Drop every laid-out copy."""
        # key (kind, input shape, geometry) -> laid-out copy of the weight seen last, at its version
        self._entries: dict[tuple, Tensor] = {}
        self._weight: weakref.ref | None = None
        self._version = -1

    def _get(self, key: tuple, weight: Tensor, make: Callable[[], Tensor]) -> Tensor:
        if self._weight is None or self._weight() is not weight or self._version != weight._version:
            self.clear()  # another weight, or this one written since: every copy is stale
            self._weight, self._version = weakref.ref(weight), weight._version
        packed = self._entries.get(key)
        if packed is None:
            while len(self._entries) >= MAX_SHAPES:
                self._entries.pop(next(iter(self._entries)))
            packed = self._entries[key] = make()
        return packed

    def _convolve(
        self,
        x: Tensor,
        weight: Tensor,
        geometry: tuple,
        make: Callable[[], Tensor],
        run: Callable[[Tensor], Tensor],
        bias: Tensor | None,
    ) -> Tensor | None:
        """``run`` on the laid-out weight (made by ``make`` once per input shape), or ``None``."""
        if not _usable(x, weight, bias):
            return None
        packed = self._get((*geometry, tuple(x.shape), x.dtype), weight, make)
        return _layout_of(run(packed), x)

    def conv2d(
        self,
        x: Tensor,
        weight: Tensor,
        bias: Tensor | None,
        stride: tuple[int, int],
        padding: tuple[int, int],
    ) -> Tensor | None:
        """``F.conv2d(x, weight, bias, stride, padding)`` on the laid-out weight, or ``None``.

        Args:
            x: ``[B, C_in, H, W]``.
            weight: ``[C_out, C_in, k, k]``, the layer's own parameter.
            bias: ``[C_out]`` or None.
            stride, padding: ``(rows, columns)``.

        Returns:
            ``[B, C_out, H_out, W_out]`` in ``x``'s memory format, or ``None`` (not applicable here).
        """
        stride, padding = [int(s) for s in stride], [int(p) for p in padding]
        return self._convolve(
            x,
            weight,
            ("conv", tuple(stride), tuple(padding)),
            lambda: torch.ops.aten.mkldnn_reorder_conv2d_weight(
                weight.detach().to_mkldnn(), padding, stride, [1, 1], 1, list(x.shape)
            ),
            lambda packed: torch.ops.mkldnn._convolution_pointwise(
                x, packed, bias, padding, stride, [1, 1], 1, "none", [], ""
            ),
            bias,
        )

    def conv_transpose2d(
        self,
        x: Tensor,
        weight: Tensor,
        bias: Tensor | None,
        stride: tuple[int, int],
        padding: tuple[int, int],
        output_padding: tuple[int, int],
    ) -> Tensor | None:
        """``F.conv_transpose2d(x, weight, bias, stride, padding, output_padding)`` on the laid-out
        weight, or ``None``.

        Args:
            x: ``[B, C_in, H, W]``.
            weight: ``[C_in, C_out, k, k]`` (the transposed convolution's layout), the layer's parameter.
            bias: ``[C_out]`` or None.
            stride, padding, output_padding: ``(rows, columns)``.

        Returns:
            ``[B, C_out, H_out, W_out]`` in ``x``'s memory format, or ``None`` (not applicable here).
        """
        stride, padding = [int(s) for s in stride], [int(p) for p in padding]
        output_padding = [int(p) for p in output_padding]
        return self._convolve(
            x,
            weight,
            ("transposed", tuple(stride), tuple(padding), tuple(output_padding)),
            lambda: torch.ops.mkldnn._reorder_convolution_transpose_weight(
                weight.detach(), padding, output_padding, stride, [1, 1], 1, list(x.shape)
            ),
            lambda packed: torch.ops.mkldnn._convolution_transpose_pointwise(
                x, packed, bias, padding, output_padding, stride, [1, 1], 1, "none", [], ""
            ),
            bias,
        )


def _layout_of(out: Tensor, x: Tensor) -> Tensor:
    """``out`` in the memory format ``F.conv2d`` gives for ``x``: channels-last only for a channels-last
    input (oneDNN's result may be channels-last for a contiguous one)."""
    if x.is_contiguous() and not out.is_contiguous():
        return out.contiguous()
    return out
