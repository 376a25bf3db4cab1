"""Top views of trajectories: the aligned estimates of :mod:`cylsfm.evaluate.pose` against the ground truth."""

from __future__ import annotations

import io

import numpy as np

from ..atomic import atomic_write_bytes
from .frames import PathLike

__all__ = ["plot_trajectories"]


def plot_trajectories(
    path: PathLike,
    gt_xyz: np.ndarray | None,
    curves: dict[str, np.ndarray | None],
    title: str = "",
    unit: str = "m",
    links: np.ndarray | None = None,
) -> None:
    """Save a top view (x right, z up the page; the world's y points down) of aligned trajectories
    ``{name: [N,3]}`` against the ground truth ``[N,3]`` (``None``: none) as a PNG (matplotlib's Agg canvas,
    written atomically; the global matplotlib backend is left alone); ``unit`` labels the axes; ``links``
    ``[K,2,3]``: pairs of points joined by thin lines (loop constraints)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    if gt_xyz is not None:
        gt = np.asarray(gt_xyz)
        ax.plot(gt[:, 0], gt[:, 2], "k-", lw=2, label="ground truth")
        ax.plot(gt[:1, 0], gt[:1, 2], "ko", ms=5)
    styles = ["-", "--", ":", "-."]
    for n, (name, xyz) in enumerate(curves.items()):
        if xyz is None:
            continue
        xyz = np.asarray(xyz)
        ax.plot(xyz[:, 0], xyz[:, 2], styles[n % len(styles)], lw=1.5, label=name)
    if links is not None and len(links):
        for n, (a, b) in enumerate(np.asarray(links)):
            ax.plot([a[0], b[0]], [a[2], b[2]], "-", color="tab:red", lw=0.7, alpha=0.6,
                    label="loop constraints" if n == 0 else None)  # fmt: skip
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"z ({unit})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(path, buf.getvalue())
