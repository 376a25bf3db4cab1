"""Split files: which target frames are used for training, validation and testing.

A split file lists target samples, one per line, ``SEQ FRAME_STEM`` (e.g. ``seq_003 000123``); ``#``
starts a comment. A dataset's splits live in ``ROOT/splits/NAME/{train,val,test}.txt``. The snippet of a
target ``t`` is the frames ``t - k*stride .. t + k*stride`` (step ``stride``) with ``k = (seq_length-1)//2``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes
from ..errors import InputError
from .format import DatasetError, SequenceInfo, find_sequence_dirs, list_images, scan_dataset
from .io import read_text

__all__ = [
    "SPLIT_PARTS",
    "check_snippet_args",
    "make_splits",
    "read_split",
    "snippet_offsets",
    "split_path",
    "split_targets",
]

#: The parts of a split, in the order of ``fractions``.
SPLIT_PARTS = ("train", "val", "test")

PathLike = str | os.PathLike[str]
Target = tuple[int, int]  # (sequence index, frame index) of a target


def check_snippet_args(seq_length: int, stride: int) -> None:
    """Raise :class:`~cylsfm.errors.InputError` unless ``seq_length`` is odd and >= 1 and ``stride`` >= 1."""
    if int(seq_length) != seq_length or seq_length < 1 or seq_length % 2 == 0:
        raise InputError(f"seq_length must be an odd integer >= 1 (target in the middle), got {seq_length}")
    if int(stride) != stride or stride < 1:
        raise InputError(f"stride must be an integer >= 1, got {stride}")


def snippet_offsets(seq_length: int, stride: int) -> np.ndarray:
    """Frame offsets ``int64 [seq_length]`` of a snippet relative to its target, in time order."""
    check_snippet_args(seq_length, stride)
    k = (seq_length - 1) // 2
    return np.arange(-k, k + 1, dtype=np.int64) * stride


def split_path(root: PathLike, part: str, name: str = "default") -> Path:
    """``ROOT/splits/NAME/PART.txt``."""
    _check_name(name, "split name")
    return Path(root) / "splits" / name / f"{part}.txt"


def split_targets(
    root: PathLike, split: PathLike, sequences: Sequence[SequenceInfo], name: str = "default"
) -> tuple[Path, list[tuple[str, str]]]:
    """The split file that ``split`` means and its targets (:func:`read_split`).

    Args:
        root: the dataset root.
        split: a part (``"train"``, ``"val"``, ``"test"``) of the split ``name`` of ``root``, whose file must
            exist, or the path of a split file.
        sequences: the scanned sequences of ``root``.
        name: which split of ``ROOT/splits`` a part refers to.

    Raises:
        DatasetError: the file of a part is missing (saying how to write it), or see :func:`read_split`.
    """
    if isinstance(split, str) and split in SPLIT_PARTS:
        path = split_path(root, split, name)
        if not path.exists():
            raise DatasetError(
                f"{path}: split file not found (write the splits with `cylsfm split {root}`, "
                "or use --split all)"
            )
    else:
        path = Path(split)
    return path, read_split(path, root, sequences)


def _check_name(name: str, what: str) -> None:
    if not name or name in (".", "..") or "/" in name or "\\" in name or os.path.isabs(name):
        raise InputError(f"invalid {what} {name!r}: must be a plain directory or file name")


def _unsafe(name: str) -> bool:
    return (
        not name
        or name in (".", "..")
        or "/" in name
        or "\\" in name
        or os.path.isabs(name)
        or name.startswith("~")
        or "\x00" in name
    )


def read_split(
    path: PathLike, root: PathLike, sequences: Sequence[SequenceInfo] | None = None
) -> list[tuple[str, str]]:
    """Read and validate a split file.

    Args:
        path: the split file.
        root: the dataset root whose sequences and frames the entries name.
        sequences: the scanned sequences (:func:`~cylsfm.data.format.scan_dataset`); listed from
            ``root`` when omitted (file names only, nothing decoded).

    Returns:
        ``[(sequence, frame_stem), ...]`` in file order.

    Raises:
        DatasetError: ``file:line`` and the problem for a malformed line, an entry that would leave the
            dataset root (absolute paths, ``..``, separators), or an unknown sequence or frame.
    """
    path = Path(path)
    text = read_text(path, "split file")
    frames: dict[str, set[str] | None]
    seq_dirs: dict[str, Path] = {}
    if sequences is not None:
        frames = {s.name: set(s.stems) for s in sequences}
    else:
        seq_dirs = {d.name: d for d in find_sequence_dirs(root)}
        frames = dict.fromkeys(seq_dirs)
    out: list[tuple[str, str]] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise DatasetError(f"{path}:{lineno}: expected 'SEQUENCE FRAME', got {raw.strip()!r}")
        seq, stem = parts
        if _unsafe(seq) or _unsafe(stem):
            raise DatasetError(f"{path}:{lineno}: entry {line!r} would leave the dataset root")
        if seq not in frames:
            raise DatasetError(f"{path}:{lineno}: unknown sequence {seq!r} in {root}")
        known = frames[seq]
        if known is None:
            known = frames[seq] = {p.stem for p in list_images(seq_dirs[seq], root)}
        if stem not in known:
            raise DatasetError(f"{path}:{lineno}: unknown frame {stem!r} of sequence {seq!r}")
        out.append((seq, stem))
    return out


def _allocate(n: int, fractions: Sequence[float]) -> list[int]:
    """Split ``n`` items by ``fractions`` (largest remainder). Every part with a positive fraction then
    gets at least one item while another part can spare one, in the order train, test, val."""
    raw = [f * n for f in fractions]
    counts = [math.floor(r) for r in raw]
    order = sorted(range(len(raw)), key=lambda i: (-(raw[i] - counts[i]), i))
    for i in order[: n - sum(counts)]:
        counts[i] += 1
    for i in (0, 2, 1):
        if fractions[i] > 0 and counts[i] == 0:
            donor = max(range(len(counts)), key=lambda j: (counts[j], -j))
            if counts[donor] > 1:
                counts[donor] -= 1
                counts[i] += 1
    return counts


def make_splits(
    root: PathLike,
    name: str = "default",
    mode: str = "sequence",
    fractions: Sequence[float] = (0.8, 0.1, 0.1),
    seed: int = 0,
    seq_length: int = 3,
    stride: int = 1,
) -> dict[str, Path]:
    """Write ``ROOT/splits/NAME/{train,val,test}.txt`` (atomically) and return their paths by part.

    Only targets with a full snippet (``seq_length``, ``stride``) are listed. Deterministic given ``seed``.

    Modes:
        ``"sequence"``: whole sequences go to train / val / test in proportion to ``fractions`` (counted
            in sequences; every part with a positive fraction gets at least one sequence when another
            part can spare one, train first, then test, then val).
        ``"frame"``: targets drawn at random by frame, with the rule of the paper: no frame of a test or
            validation snippet is used in training, as a target or as a source. Test targets are drawn
            first (``fractions[2]`` of all candidate targets), then validation targets whose snippets
            share no frame with a test snippet, then every remaining target whose snippet touches no test
            or validation frame goes to training (at most ``fractions[0]`` of the candidates). The frames
            around held-out snippets are lost to training (each isolated held-out target removes up to
            ``4 k stride + 1`` training targets), so the training part is usually smaller than its
            fraction: keep the held-out fractions small. Use the same ``seq_length`` and ``stride`` for
            training as here.

    Args:
        root: dataset root.
        name: split name (a directory under ``ROOT/splits``).
        mode: ``"sequence"`` or ``"frame"``.
        fractions: ``(train, val, test)``, non-negative, summing to 1.
        seed: random seed.
        seq_length, stride: the snippet shape (see the module docstring).

    Raises:
        InputError: for an invalid name, mode, fractions or snippet shape.
        DatasetError: for an invalid dataset (see :func:`~cylsfm.data.format.scan_dataset`).
    """
    _check_name(name, "split name")
    check_snippet_args(seq_length, stride)
    fr = [float(f) for f in fractions]
    if len(fr) != 3 or any(f < 0 or not math.isfinite(f) for f in fr) or abs(sum(fr) - 1) > 1e-6:
        raise InputError(f"fractions must be 3 non-negative numbers summing to 1, got {tuple(fractions)}")
    if mode not in ("sequence", "frame"):
        raise InputError(f"mode must be 'sequence' or 'frame', got {mode!r}")
    seqs = scan_dataset(root)
    rng = np.random.default_rng(seed)
    if mode == "sequence":
        parts = _split_by_sequence([len(seq) for seq in seqs], fr, rng, (seq_length - 1) // 2 * stride)
    else:
        parts = _split_by_frame([len(seq) for seq in seqs], fr, rng, snippet_offsets(seq_length, stride))
    settings = (
        f"mode={mode} seed={seed} seq_length={seq_length} stride={stride} "
        f"fractions={','.join(f'{f:g}' for f in fr)}"
    )
    out: dict[str, Path] = {}
    for p, part in enumerate(SPLIT_PARTS):
        lines = [f"# cylsfm split {name} / {part}: {settings}\n", "# SEQUENCE FRAME\n"]
        lines += [f"{seqs[s].name} {seqs[s].images[t].stem}\n" for s, t in sorted(parts[p])]
        path = split_path(root, part, name)
        atomic_write_bytes(path, "".join(lines).encode())
        out[part] = path
    return out


def _split_by_sequence(
    lengths: list[int], fr: list[float], rng: np.random.Generator, reach: int
) -> list[list[Target]]:
    """Whole sequences (of ``lengths`` frames) to train / val / test; every target ``reach`` frames from
    the sequence's ends is listed."""
    parts: list[list[Target]] = [[], [], []]
    counts = _allocate(len(lengths), fr)
    perm = rng.permutation(len(lengths))
    start = 0
    for p, c in enumerate(counts):
        for s in sorted(perm[start : start + c].tolist()):
            parts[p].extend((s, t) for t in range(reach, lengths[s] - reach))
        start += c
    return parts


def _split_by_frame(
    lengths: list[int], fr: list[float], rng: np.random.Generator, offsets: np.ndarray
) -> list[list[Target]]:
    """Targets drawn at random; no frame of a held-out snippet (``t + offsets``) in a training snippet."""
    reach = int(offsets[-1])
    parts: list[list[Target]] = [[], [], []]
    cands = [(s, t) for s, n in enumerate(lengths) for t in range(reach, n - reach)]
    m = len(cands)
    want = [round(f * m) for f in fr]
    for p in (1, 2):
        if fr[p] > 0 and want[p] == 0 and m > 0:
            want[p] = 1
    held = [np.zeros(n, dtype=bool) for n in lengths]
    taken = np.zeros(m, dtype=bool)
    perm = rng.permutation(m)
    # test first, then validation: each held-out snippet marks its frames; a validation snippet
    # may not touch a test frame, a training snippet no held-out frame at all.
    for p in (2, 1):
        frozen = [h.copy() for h in held]
        for idx in perm:
            if len(parts[p]) >= want[p]:
                break
            if taken[idx]:
                continue
            s, t = cands[idx]
            frames = t + offsets
            if frozen[s][frames].any():
                continue
            taken[idx] = True
            held[s][frames] = True
            parts[p].append((s, t))
    train = [idx for idx in perm if not taken[idx] and not held[cands[idx][0]][cands[idx][1] + offsets].any()]
    parts[0] = [cands[i] for i in train[: want[0]]]
    return parts
