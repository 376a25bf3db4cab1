"""Convolutions of the deepest, smallest feature maps, computed as matrix products when that is faster.

SfMLearner's DispNet ends its encoder and starts its decoder on feature maps of one or two rows and a few
columns (``1 x 4``, ``2 x 8`` at 512x128) with the network's largest weights (``512 x 1024 x 3 x 3``).
On the CPU, oneDNN's convolution backward re-lays these weights out on every call and runs such tiny maps
at a fraction of its usual rate; the same convolution as ``unfold`` + one matrix product (and its
autograd backward: two matrix products and a ``fold``) is 2-2.6x faster there.  A one-row input with one
row of zero padding above and below only ever meets the kernel's middle row, so only that row is used
(the others' gradients are exactly zero either way): a third of the work.

Both functions compute exactly what ``F.conv2d`` / ``F.conv_transpose2d`` compute, up to float rounding
(tested); they choose the matrix product only on the CPU, while gradients are recorded, for outputs (for
the transposed convolution: inputs) of at most :data:`MAX_POSITIONS` positions per image.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .packed import PackedWeights

__all__ = ["MAX_POSITIONS", "conv2d_rows_padded", "conv_transpose2d_small"]

#: Largest output (rows x columns per image) computed as a matrix product; measured on an AVX2 CPU:
#: 16 positions 2.1x faster than oneDNN forward + backward, 64 positions 1.2x slower.  0 turns both
#: functions into plain ``F.conv2d`` / ``F.conv_transpose2d`` (the benchmarks' "before").
MAX_POSITIONS = 32


def _matmul_wanted(x: Tensor, positions: int) -> bool:
    return x.device.type == "cpu" and torch.is_grad_enabled() and positions <= MAX_POSITIONS


def conv2d_rows_padded(
    x: Tensor,
    weight: Tensor,
    bias: Tensor | None,
    stride: int | tuple[int, int],
    pad_rows: int,
    packed: PackedWeights | None = None,
) -> Tensor:
    """``F.conv2d(x, weight, bias, stride, padding=(pad_rows, 0))``, faster on tiny maps.

    Args:
        x: ``[B, C_in, H, W]``, any horizontal padding already applied.
        weight: ``[C_out, C_in, k, k]``.
        bias: ``[C_out]`` or None.
        stride: stride (both directions, or ``(rows, columns)``).
        pad_rows: zero rows added above and below.
        packed: the layer's :class:`~cylsfm.nn.packed.PackedWeights` (``weight`` its own parameter):
            at inference on the CPU the convolution runs on its laid-out weight.

    Returns:
        ``[B, C_out, H_out, W_out]`` with ``H_out = (H + 2 pad_rows - k) // s + 1``,
        ``W_out = (W - k) // s + 1``.
    """
    sh, sw = (stride, stride) if isinstance(stride, int) else stride
    if packed is not None:
        out = packed.conv2d(x, weight, bias, (sh, sw), (pad_rows, 0))
        if out is not None:
            return out
    k_rows, k_cols = weight.shape[-2:]
    height, width = x.shape[-2:]
    if MAX_POSITIONS and height == 1 and k_rows == 2 * pad_rows + 1:
        # one row, centred kernel: the rows above and below are zeros, only the middle row counts
        weight = weight[:, :, pad_rows : pad_rows + 1]
        k_rows, pad_rows = 1, 0
    rows = (height + 2 * pad_rows - k_rows) // sh + 1
    cols = (width - k_cols) // sw + 1
    if not _matmul_wanted(x, rows * cols):
        return F.conv2d(x, weight, bias, (sh, sw), (pad_rows, 0))
    patches = F.unfold(x, (k_rows, k_cols), padding=(pad_rows, 0), stride=(sh, sw))  # B, C k k, L
    out = torch.matmul(weight.reshape(weight.shape[0], -1), patches)  # B, C_out, L
    if bias is not None:
        out = out + bias[:, None]
    return _like(out.reshape(x.shape[0], weight.shape[0], rows, cols), x)


def conv_transpose2d_small(
    x: Tensor,
    weight: Tensor,
    bias: Tensor | None,
    stride: tuple[int, int],
    padding: tuple[int, int],
    output_padding: tuple[int, int],
    packed: PackedWeights | None = None,
) -> Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride, padding, output_padding)``, faster on tiny maps.

    Args:
        x: ``[B, C_in, H, W]``.
        weight: ``[C_in, C_out, k, k]`` (the transposed convolution's layout).
        bias: ``[C_out]`` or None.
        stride, padding, output_padding: as for ``F.conv_transpose2d``.
        packed: the layer's :class:`~cylsfm.nn.packed.PackedWeights` (see :func:`conv2d_rows_padded`).

    Returns:
        ``[B, C_out, H_out, W_out]``, ``H_out = (H - 1) s - 2 p + k + output_padding``, likewise ``W_out``.
    """
    if packed is not None:
        out = packed.conv_transpose2d(x, weight, bias, stride, padding, output_padding)
        if out is not None:
            return out
    k_rows, k_cols = weight.shape[-2:]
    height, width = x.shape[-2:]
    if not _matmul_wanted(x, height * width):
        return F.conv_transpose2d(x, weight, bias, stride, padding, output_padding)
    rows = (height - 1) * stride[0] - 2 * padding[0] + k_rows + output_padding[0]
    cols = (width - 1) * stride[1] - 2 * padding[1] + k_cols + output_padding[1]
    c_out = weight.shape[1]
    # every input position scatters its kernel-sized patch: fold sums the overlapping patches
    patches = torch.matmul(weight.reshape(weight.shape[0], -1).t(), x.reshape(*x.shape[:2], -1))
    out = F.fold(patches, (rows, cols), (k_rows, k_cols), padding=padding, stride=stride)
    if bias is not None:
        out = out + bias.reshape(1, c_out, 1, 1)
    return _like(out, x)


def _like(out: Tensor, x: Tensor) -> Tensor:
    """``out`` in channels-last memory when ``x`` is (as oneDNN's result would be)."""
    if x.dim() == 4 and x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous():
        return out.contiguous(memory_format=torch.channels_last)
    return out
