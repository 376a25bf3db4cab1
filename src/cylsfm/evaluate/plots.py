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
) -> None:
    """Save a top view (x right, z up the page; the world's y points down) of aligned trajectories
    ``{name: [N,3]}`` against the ground truth ``[N,3]`` (``None``: none) as a PNG (matplotlib's Agg canvas,
    written atomically; the global matplotlib backend is left alone); ``unit`` labels the axes."""
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
