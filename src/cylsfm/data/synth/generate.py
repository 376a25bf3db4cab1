"""Writing a generated dataset: one town and ride a sequence, frames rendered by a pool of processes."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError
from ...geometry import Camera
from ...runtime import progress_bar
from ..format import SequenceWriter
from ..splits import make_splits, split_path
from .config import SynthConfig
from .occluder import OCCLUDERS, occluder_mask, occluder_texture
from .render import make_camera, render_frame
from .ride import ROUTES
from .town import StreetScene

__all__ = ["generate_dataset"]


def generate_dataset(
    out: str | os.PathLike[str],
    sequences: int = 4,
    frames: int = 200,
    width: int = 512,
    height: int = 128,
    seed: int = 0,
    moving_objects: bool = False,
    projection: str = "cylindrical",
    workers: int | None = None,
    config: SynthConfig | None = None,
    progress: bool = True,
    first_index: int = 0,
    overwrite: bool = False,
    splits: bool = False,
    split_fractions: Sequence[float] = (0.8, 0.1, 0.1),
    occluder: str = "none",
) -> list[Path]:
    """Write ``sequences`` rides of ``frames`` frames each to ``out/seq_NNN`` in dataset format v1.

    Each sequence is a different town and ride (seeded by ``seed`` and the sequence index ``NNN``, which
    counts from ``first_index``), so the same arguments give the same files bit for bit. Frames are
    rendered in parallel by ``workers`` processes (default or 0: the number of CPUs).

    Args:
        out: the dataset root (created).
        sequences, frames: how many rides, and frames a ride (at least 3: a target and two sources).
        width, height: the image size in pixels.
        seed: the seed of the towns and rides (and of the split).
        moving_objects: add 12 cars driving through each town (unless ``config`` sets ``moving_cars``).
        projection: ``"cylindrical"``, ``"equirect"`` or ``"pinhole"`` (see :func:`make_camera`).
        workers: render processes.
        config: the town and ride parameters (``frames`` is taken from the argument).
        progress: show a progress bar per sequence.
        first_index: the index of the first sequence (to add rides to an existing root).
        overwrite: replace sequences ``out/seq_NNN`` that already exist (and the split, see below).
        splits: also write the split ``out/splits/default/{train,val,test}.txt`` by sequence, so that
            training and evaluation can start right away. The rule: whole rides are held out; every
            sequence in ``out`` (the ones written now and any that were there) goes to train, val or test
            in proportion to ``split_fractions`` (counted in sequences, each part with a positive
            fraction gets at least one when another can spare one), chosen at random with ``seed`` by
            :func:`~cylsfm.data.splits.make_splits` (``mode="sequence"``, snippets of 3 frames). An
            existing split of that name is kept safe: without ``overwrite`` the call stops before
            rendering anything; with it the split is written again over all the sequences in ``out``
            (adding sequences with ``first_index`` may therefore move earlier ones between parts).
        split_fractions: ``(train, val, test)``, non-negative, summing to 1.
        occluder: ``"none"``, ``"helmet"`` or ``"roof"``: an object fixed to the camera in every frame
            (:mod:`.occluder`), with no ground-truth depth (0) and left out by each sequence's
            ``mask.png``.

    Returns:
        The sequence directories written.

    Raises:
        InputError: an argument out of range (``sequences``, ``frames``, ``width``, ``height`` below 1,
            ``frames`` below 3, a negative ``first_index`` or ``workers``, ``config.supersample`` below 1,
            an unknown ``projection``, ``occluder`` or ``config.route``, invalid ``split_fractions``, no such
            route in the town), or a sequence or split already in ``out`` without ``overwrite``.
    """
    out = Path(out)
    base = config or SynthConfig()
    _check_args(
        sequences, frames, width, height, first_index, workers, base, splits, split_fractions, occluder
    )
    camera = make_camera(projection, width, height)
    occ = occluder_mask(width, height, occluder) if occluder != "none" else None
    seq_dirs = [out / f"seq_{n:03d}" for n in range(first_index, first_index + sequences)]
    if not overwrite:
        _refuse_existing(out, seq_dirs, splits)
    out.mkdir(parents=True, exist_ok=True)
    workers = workers or os.cpu_count() or 1
    cfg = replace(base, frames=frames, moving_cars=base.moving_cars or (12 if moving_objects else 0))
    for n, seq_dir in zip(range(first_index, first_index + sequences), seq_dirs, strict=True):
        scene = StreetScene.generate(int(np.random.SeedSequence([seed, n]).generate_state(1)[0]), cfg)
        writer = SequenceWriter(seq_dir, camera, overwrite=overwrite)
        _render_into(writer, scene, camera, frames, workers, progress, occ)
        writer.finish(scene.c2w, np.arange(frames) / cfg.fps, mask=None if occ is None else ~occ)
    if splits:
        make_splits(out, mode="sequence", fractions=tuple(split_fractions), seed=seed)
    return seq_dirs


def _check_args(
    sequences: int,
    frames: int,
    width: int,
    height: int,
    first_index: int,
    workers: int | None,
    config: SynthConfig,
    splits: bool,
    split_fractions: Sequence[float],
    occluder: str,
) -> None:
    """Raise :class:`InputError` for an argument of :func:`generate_dataset` out of range."""
    if occluder not in OCCLUDERS:
        raise InputError(f"occluder must be one of {', '.join(OCCLUDERS)}, got {occluder!r}")
    for name, value in (("sequences", sequences), ("frames", frames), ("width", width), ("height", height)):
        if value < 1:
            raise InputError(f"{name} must be at least 1, got {value}")
    if frames < 3:
        raise InputError(f"frames must be at least 3 (a target and two sources), got {frames}")
    if first_index < 0:
        raise InputError(f"first_index must be at least 0, got {first_index}")
    if workers is not None and workers < 0:
        raise InputError(f"workers must be at least 1 (or 0 for one per CPU), got {workers}")
    if config.supersample < 1:
        raise InputError(f"supersample must be at least 1, got {config.supersample}")
    if config.route not in ROUTES:
        raise InputError(f"route must be one of {', '.join(ROUTES)}, got {config.route!r}")
    if config.town_frames < 0:
        raise InputError(f"town_frames must be at least 0, got {config.town_frames}")
    if splits:
        fr = [float(f) for f in split_fractions]
        if len(fr) != 3 or any(f < 0 or not math.isfinite(f) for f in fr) or abs(sum(fr) - 1) > 1e-6:
            raise InputError(
                f"split fractions must be 3 non-negative numbers summing to 1, got {tuple(split_fractions)}"
            )


def _refuse_existing(out: Path, seq_dirs: list[Path], splits: bool) -> None:
    """Raise :class:`InputError` if a sequence of ``seq_dirs`` (or, with ``splits``, the default split)
    already exists: the check of :class:`~cylsfm.data.format.SequenceWriter`, made before rendering."""
    for d in seq_dirs:
        images = d / "images"
        if (d / "camera.json").exists() or (images.is_dir() and any(images.iterdir())):
            raise InputError(f"{d}: already holds a sequence (overwrite to replace it)")
    if splits:
        for part in ("train", "val", "test"):
            path = split_path(out, part)
            if path.exists():
                raise InputError(
                    f"{path}: a split already exists (overwrite to write it again over all the sequences "
                    f"in {out}, or do not write splits)"
                )


def _render_into(
    writer: SequenceWriter,
    scene: StreetScene,
    camera: Camera,
    frames: int,
    workers: int,
    progress: bool,
    occluder: np.ndarray | None = None,
) -> None:
    """Render the ``frames`` frames of ``scene`` and add them to ``writer`` in order, by ``workers``
    processes (1: in this process), counting them on a progress bar. ``occluder`` ``bool [H,W]``: the
    pixels painted with the occluder's texture (their depth unknown)."""
    bar = progress_bar(total=frames, desc=writer.path.name, unit="frame", enabled=progress, leave=False)
    try:
        _render_frames(writer, scene, camera, frames, workers, bar, occluder)
    finally:
        bar.close()


def _render_frames(
    writer: SequenceWriter,
    scene: StreetScene,
    camera: Camera,
    frames: int,
    workers: int,
    bar,
    occluder: np.ndarray | None,
) -> None:
    from concurrent.futures import ProcessPoolExecutor

    texture = occluder_texture(*camera.size) if occluder is not None else None

    def add(image: np.ndarray, depth: np.ndarray) -> None:
        if occluder is not None:
            image = np.where(occluder[..., None], texture, image)
            depth = np.where(occluder, np.float32(0), depth)
        writer.add_frame(image, depth)
        bar.update(1)

    if workers <= 1:
        _init_worker(scene, camera)
        for f in range(frames):
            _, image, depth = _render_job(f)
            add(image, depth)
        return
    results: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    nxt = 0
    with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(scene, camera)) as pool:
        for f, image, depth in pool.map(_render_job, range(frames), chunksize=4):
            results[f] = (image, depth)
            while nxt in results:
                add(*results.pop(nxt))
                nxt += 1


_WORKER: dict[str, Any] = {}  # the scene and camera of a render process


def _init_worker(scene: StreetScene, camera: Camera) -> None:
    import torch

    torch.set_num_threads(1)  # one process per core: no threads inside
    _WORKER["scene"], _WORKER["camera"] = scene, camera


def _render_job(frame: int) -> tuple[int, np.ndarray, np.ndarray]:
    image, depth = render_frame(_WORKER["scene"], frame, _WORKER["camera"])
    return frame, image, depth
