"""A resumable, shardable, endless sampler with a seed per sample.

The data order is a pure function of ``(seed, epoch)``, so a run resumed from a checkpoint continues
with exactly the samples it would have seen; every sample also carries its own random seed, used for its
augmentation, so resumed runs (and any number of loader workers) augment identically.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import torch
from torch.utils.data import Dataset, Sampler

__all__ = ["ResumableSampler", "SeededDataset"]


class ResumableSampler(Sampler[tuple[int, int]]):
    """Endless shuffled epochs over ``n`` samples, sharded over ``world`` ranks.

    Yields ``(index, sample_seed)``. Each epoch is a permutation drawn from ``seed + epoch``; rank ``r``
    takes every ``world``-th element starting at ``r`` (the last partial round is dropped so ranks stay in
    step). ``start`` skips that many samples of this rank's stream (resuming after ``start`` samples).
    """

    def __init__(self, n: int, seed: int = 0, rank: int = 0, world: int = 1, start: int = 0) -> None:
        if n < world:
            raise ValueError(f"{n} samples cannot be shared by {world} processes")
        self.n, self.seed, self.rank, self.world, self.start = n, seed, rank, world, start
        self.per_epoch = n // world

    def position(self, consumed: int) -> tuple[int, int]:
        """``(epoch, offset)`` after ``consumed`` samples of this rank."""
        return divmod(consumed, self.per_epoch)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch, offset = self.position(self.start)
        while True:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
            perm = torch.randperm(self.n, generator=g)[: self.per_epoch * self.world]
            seeds = torch.randint(0, 2**62, (self.n,), generator=g)
            mine = perm[self.rank :: self.world]
            for i in range(offset, self.per_epoch):
                idx = int(mine[i])
                yield idx, int(seeds[idx])
            epoch, offset = epoch + 1, 0

    def __len__(self) -> int:  # an endless stream; this is the length of one epoch of this rank
        return self.per_epoch


class SeededDataset(Dataset):
    """Wraps a dataset so that ``ds[(index, seed)]`` draws its augmentation from ``seed``."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, key: tuple[int, int]) -> Any:
        index, seed = key
        torch.manual_seed(seed)
        return self.dataset[index]
