"""The snippets of a dataset: which frames every training or evaluation sample is made of.

:func:`build_index` scans a dataset once (:func:`~cylsfm.data.format.scan_dataset`), removes bad and static
frames (:mod:`cylsfm.data.static`), forms every full snippet over the frames left and keeps those whose
targets a split lists (:mod:`cylsfm.data.splits`). The :class:`SnippetIndex` it returns is all a
:class:`~cylsfm.data.dataset.SequenceDataset` needs to know of the dataset's layout; it decodes nothing but
the thumbnails of the image static filter.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .format import DatasetWarning, SequenceInfo, scan_dataset
from .splits import snippet_offsets, split_targets
from .static import StaticFilter, kept_runs

__all__ = ["SnippetIndex", "build_index"]


@dataclass(frozen=True)
class SnippetIndex:
    """Every snippet of a dataset, in sample order.

    Attributes:
        root: the dataset root (or single sequence directory) scanned.
        sequences: its sequences, as scanned (frames found bad while building are in each ``bad``).
        frames: ``int64 [N, seq_length]``, the frame indices of each snippet in time order.
        owners: ``int64 [N]``, the index in ``sequences`` of each snippet's sequence.
        skip_bad: whether bad frames were skipped (with a warning) rather than refused; a dataset of this
            index then also replaces a sample whose frame fails to decode by the next loadable one.
        used: the indices of the sequences that hold a snippet, in order (made from ``owners``).
    """

    root: Path
    sequences: list[SequenceInfo]
    frames: np.ndarray
    owners: np.ndarray
    skip_bad: bool = False
    used: list[int] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "used", sorted(set(self.owners.tolist())))

    @property
    def seq_length(self) -> int:
        """Frames per snippet."""
        return int(self.frames.shape[1])

    @property
    def center(self) -> int:
        """The target's position in a snippet."""
        return self.seq_length // 2

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def targets(self) -> list[tuple[str, str]]:
        """``(sequence, frame)`` of every snippet's target, in index order."""
        return [
            (self.sequences[s].name, self.sequences[s].images[row[self.center]].stem)
            for s, row in zip(self.owners.tolist(), self.frames, strict=True)
        ]

    def snippet(self, index: int) -> tuple[str, list[str]]:
        """``(sequence, frame names of the snippet in time order)`` of snippet ``index``."""
        seq = self.sequences[int(self.owners[index])]
        return seq.name, [seq.images[f].stem for f in self.frames[index]]


def build_index(
    root: str | os.PathLike[str],
    split: str | os.PathLike[str] | None = None,
    split_name: str = "default",
    seq_length: int = 3,
    stride: int = 1,
    static: StaticFilter | None = None,
    skip_bad: bool = False,
) -> SnippetIndex:
    """The snippets of the dataset at ``root`` (see the module docstring).

    Args:
        root: dataset root (or a single sequence directory).
        split: ``None`` for every target with a full snippet; ``"train"``, ``"val"`` or ``"test"`` for
            ``ROOT/splits/<split_name>/<split>.txt``; or the path of a split file. Listed targets without
            a full snippet here (static frame, sequence border, bad frame) are skipped with one warning.
        split_name: which split of ``ROOT/splits`` a named split refers to.
        seq_length: frames per snippet (odd); the snippet of target ``t`` is
            ``t - k*stride .. t + k*stride`` with ``k = (seq_length - 1) // 2``, counted over the frames
            left after static-frame removal.
        stride: frame step within a snippet.
        static: :class:`StaticFilter`; default ``StaticFilter(method="none")``.
        skip_bad: drop frames whose header is bad (with a :class:`DatasetWarning`; no snippet contains
            them) instead of raising :class:`DatasetError`.

    Raises:
        DatasetError: naming the file, for any invalid input (see :func:`scan_dataset`), or a named split
            whose file does not exist.
        InputError: for an invalid ``seq_length`` or ``stride``; a ``ValueError`` too.
    """
    offsets = snippet_offsets(seq_length, stride)  # checks them
    static = static if static is not None else StaticFilter(method="none")
    root = Path(root)
    sequences = scan_dataset(root, skip_bad=skip_bad)
    frames, owners = _snippet_table(sequences, offsets, static, skip_bad)
    if split is not None:
        path, entries = split_targets(root, split, sequences, split_name)
        chosen = _listed(entries, sequences, frames[:, len(offsets) // 2], owners)
        listed = len(entries)
        if len(chosen) < listed:
            warnings.warn(
                f"{path}: {listed - len(chosen)} of {listed} targets have no full snippet "
                f"(seq_length={seq_length}, stride={stride}, static={static.method}) and are skipped",
                DatasetWarning,
                stacklevel=2,
            )
        frames, owners = (frames[chosen] if len(chosen) else frames[:0]), owners[chosen]
    if len(frames) == 0:
        warnings.warn(
            f"{root}: no samples (no target has a full snippet of seq_length={seq_length}, "
            f"stride={stride}{'' if split is None else f' in split {split}'})",
            DatasetWarning,
            stacklevel=2,
        )
    return SnippetIndex(root, sequences, frames, owners, skip_bad)


def _snippet_table(
    sequences: list[SequenceInfo], offsets: np.ndarray, static: StaticFilter, skip_bad: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Every full snippet over the frames left after bad-frame and static-frame removal: ``(frames int64
    [N, seq_length], sequence int64 [N])``, the frame indices of each snippet and the index of its
    sequence."""
    reach = int(offsets[-1])  # positions in the list of kept frames
    tables: list[np.ndarray] = [np.zeros((0, len(offsets)), dtype=np.int64)]
    owners: list[np.ndarray] = [np.zeros(0, dtype=np.int64)]
    for s, seq in enumerate(sequences):
        # the warnings of skipped frames point at the caller of build_index
        for kept in kept_runs(seq, static, skip_bad, stacklevel=3):
            if len(kept) <= 2 * reach:
                continue
            pos = np.arange(reach, len(kept) - reach)[:, None] + offsets[None, :]
            tables.append(np.asarray(kept, dtype=np.int64)[pos])
            owners.append(np.full(len(pos), s, dtype=np.int64))
    return np.concatenate(tables), np.concatenate(owners)


def _listed(
    entries: list[tuple[str, str]], sequences: list[SequenceInfo], centres: np.ndarray, owners: np.ndarray
) -> np.ndarray:
    """The snippets (rows) whose targets (``centres``, frames of sequences ``owners``) a split lists
    (``entries``: ``(sequence, frame)``), in the split's order."""
    seq_of_name = {seq.name: i for i, seq in enumerate(sequences)}
    frame_of = [{stem: i for i, stem in enumerate(seq.stems)} for seq in sequences]
    where = {(s, f): n for n, (s, f) in enumerate(zip(owners.tolist(), centres.tolist(), strict=True))}
    chosen = []
    for seq_name, stem in entries:
        s = seq_of_name[seq_name]
        n = where.get((s, frame_of[s][stem]))
        if n is not None:
            chosen.append(n)
    return np.asarray(chosen, dtype=np.int64)
