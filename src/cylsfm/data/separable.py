"""Exact area resampling between full panoramas whose map is separable (equirectangular or cylindrical
into cylindrical, sharing their axes).

When both cameras cover a full turn about the same vertical axis, a destination column depends only on
the azimuth ``theta`` (linear in both) and a destination row only on the elevation (``h`` on a cylinder,
``phi = atan(h)`` on an equirectangular image). Resampling is then two 1-D linear maps, one along the
rows and one along the columns, each a handful of taps per output pixel. Every tap's weight is the exact
overlap of the destination pixel's footprint with a source pixel (a box filter: area averaging when
shrinking); a destination pixel smaller than a source pixel takes a one-pixel-wide box around its centre,
which is linear interpolation. This is both better filtered and an order of magnitude faster than
supersampled 2-D bilinear sampling (``benchmarks/bench_prepare.py``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError
from ..geometry import Camera, CylindricalCamera, EquirectangularCamera

__all__ = ["SeparableMap", "separable"]


def _scalar(p: object) -> float | None:
    if isinstance(p, Tensor):
        return float(p.reshape(-1)[0]) if p.numel() == 1 else None
    return float(p)  # type: ignore[arg-type]


def separable(src: Camera, dst: Camera) -> bool:
    """Whether :class:`SeparableMap` applies: a full-turn cylinder ``dst`` and a full-turn equirectangular or
    cylindrical ``src``, with scalar intrinsics."""
    kinds = isinstance(dst, CylindricalCamera) and isinstance(src, EquirectangularCamera | CylindricalCamera)
    if not kinds or not (src.wraps and dst.wraps):
        return False
    return all(_scalar(getattr(c, n)) is not None for c in (src, dst) for n in ("fx", "cx", "fy", "cy"))


def _taps(
    n_dst: int, n_src: int, to_src: Callable[[np.ndarray], np.ndarray], wrap: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """Box-filter taps of a monotonic 1-D map from destination to source pixel coordinates.

    Returns ``(index [K,n_dst] int64, weight [K,n_dst] float32, valid [n_dst] bool)``: destination pixel
    ``i`` is ``sum_k weight[k,i] * source[index[k,i]]``. Pixel ``j`` covers ``[j - 1/2, j + 1/2]``. Without
    ``wrap``, the part of a footprint outside the source is left out and the pixel is valid when at least
    half of its footprint is inside.
    """
    i = np.arange(n_dst, dtype=np.float64)
    lo, hi, centre = to_src(i - 0.5), to_src(i + 0.5), to_src(i)
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    small = hi - lo < 1.0
    lo, hi = np.where(small, centre - 0.5, lo), np.where(small, centre + 0.5, hi)
    first = np.floor(lo + 0.5).astype(np.int64)
    k_max = int(np.max(np.floor(hi + 0.5).astype(np.int64) - first)) + 1
    j = first[None, :] + np.arange(k_max)[:, None]
    overlap = np.clip(np.minimum(hi, j + 0.5) - np.maximum(lo, j - 0.5), 0.0, None)
    if wrap:
        index = np.mod(j, n_src)
        valid = np.ones(n_dst, dtype=bool)
    else:
        inside = (j >= 0) & (j < n_src)
        overlap = np.where(inside, overlap, 0.0)
        index = np.clip(j, 0, n_src - 1)
        valid = overlap.sum(0) >= 0.5 * (hi - lo)
    weight = overlap / np.maximum(overlap.sum(0, keepdims=True), 1e-12)
    weight = np.where(valid[None, :], weight, 0.0)
    return torch.from_numpy(index), torch.from_numpy(weight.astype(np.float32)), torch.from_numpy(valid)


class SeparableMap:
    """The row and column taps from ``src`` to ``dst`` (see :func:`separable`), applied to batches.

    Args:
        src: equirectangular or cylindrical full panorama camera.
        dst: cylindrical full panorama camera.
    """

    def __init__(self, src: Camera, dst: CylindricalCamera) -> None:
        sfx, scx, sfy, scy = (_scalar(getattr(src, n)) for n in ("fx", "cx", "fy", "cy"))
        dfx, dcx, dfy, dcy = (_scalar(getattr(dst, n)) for n in ("fx", "cx", "fy", "cy"))
        assert None not in (sfx, scx, sfy, scy, dfx, dcx, dfy, dcy)
        equirect = isinstance(src, EquirectangularCamera)

        def columns(u: np.ndarray) -> np.ndarray:
            return sfx * ((u - dcx) / dfx) + scx  # type: ignore[operator]

        def rows(v: np.ndarray) -> np.ndarray:
            h = (v - dcy) / dfy  # type: ignore[operator]
            return sfy * (np.arctan(h) if equirect else h) + scy  # type: ignore[operator]

        col_index, col_weight, _ = _taps(dst.width, src.width, columns, wrap=True)
        row_index, row_weight, self.row_valid = _taps(dst.height, src.height, rows, wrap=False)
        read = row_index[row_weight > 0]
        # only the band of source rows some tap reads is converted to float
        self.first_row = int(read.min()) if read.numel() else 0
        last_row = int(read.max()) + 1 if read.numel() else 1
        band = (row_index - self.first_row).clamp(0, last_row - self.first_row - 1)
        self.rows = _csr(band, row_weight, last_row - self.first_row)
        self.columns = _csr(col_index, col_weight, src.width)
        self.src_size, self.dst_size = src.size, dst.size
        self._buffers: dict[int, tuple[Tensor, ...]] = {}

    def frame(self, frame: np.ndarray) -> np.ndarray:
        """One ``uint8 [H,W,C]`` frame (channel-last, as decoded) -> ``uint8 [H',W',C]``, rounded.

        The float intermediates are kept between calls (no fresh allocation per frame, which costs more
        than the arithmetic at 3840x1920); the result is a new array. Rows without a source are 0.
        """
        (w_in, h_in), (w_out, h_out) = self.src_size, self.dst_size
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[:2] != (h_in, w_in):
            raise InputError(f"a frame must be uint8 [{h_in},{w_in},C], got {frame.dtype} {frame.shape}")
        c = frame.shape[2]
        if c not in self._buffers:
            n_band = self.rows.shape[1]
            self._buffers[c] = (
                torch.empty(n_band, w_in * c),
                torch.empty(h_out, w_in * c),
                torch.empty(w_in, h_out * c),
                torch.empty(w_out, h_out * c),
                torch.empty(h_out, w_out, c),
            )
        band, by_rows, by_cols, out, hwc = self._buffers[c]
        with warnings.catch_warnings():  # decoded frames may be read-only; they are only read here
            warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
            rows = torch.from_numpy(frame)[self.first_row : self.first_row + band.shape[0]]
        band.copy_(rows.reshape(band.shape[0], -1))
        torch.mm(self.rows, band, out=by_rows)
        by_cols.view(w_in, h_out, c).copy_(by_rows.view(h_out, w_in, c).transpose(0, 1))
        torch.mm(self.columns, by_cols, out=out)
        hwc.copy_(out.view(w_out, h_out, c).transpose(0, 1))
        return hwc.clamp_(0, 255).round_().to(torch.uint8).numpy()

    def __call__(self, image: Tensor) -> tuple[Tensor, Tensor]:
        """``image [B,C,H,W]`` (any dtype) -> ``(float [B,C,H',W'], mask [B,1,H',W'] bool)``.

        The result is a strided view (its memory is ``[W',H',B,C]``); integer images give float32.
        """
        b, c = image.shape[:2]
        (w_out, h_out), n_band = self.dst_size, self.rows.shape[1]
        dtype = image.dtype if image.is_floating_point() else torch.float32
        # [H,B,W,C]: rows first, then every pixel's channels side by side (a view of channel-last memory)
        band = image.permute(2, 0, 3, 1)[self.first_row : self.first_row + n_band].to(dtype)
        by_rows = _matrix(self.rows, band) @ band.reshape(n_band, -1)  # [H',B*W*C]
        by_cols = by_rows.view(h_out, b, -1, c).permute(2, 0, 1, 3).reshape(image.shape[-1], -1)
        out = (_matrix(self.columns, by_cols) @ by_cols).view(w_out, h_out, b, c).permute(2, 3, 1, 0)
        mask = self.row_valid.to(image.device).view(1, 1, -1, 1).expand(b, 1, -1, w_out)
        return out, mask


def _csr(index: Tensor, weight: Tensor, n_src: int) -> Tensor:
    """The ``[n_dst, n_src]`` sparse (CSR) matrix of taps ``index, weight [K,n_dst]`` (taps on one source
    pixel summed, zero taps left out)."""
    n = index.shape[1]
    dst = torch.arange(n).expand_as(index)
    keep = weight != 0
    coo = torch.sparse_coo_tensor(
        torch.stack((dst[keep], index[keep])), weight[keep], size=(n, n_src), check_invariants=True
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return coo.coalesce().to_sparse_csr()


def _matrix(m: Tensor, like: Tensor) -> Tensor:
    return (
        m if (m.device, m.dtype) == (like.device, like.dtype) else m.to(device=like.device, dtype=like.dtype)
    )
