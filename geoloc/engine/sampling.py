"""Seeded, DDP-aware sampling whose keys carry the epoch, so augmentation is reproducible anywhere."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Sampler


class EpochSampler(Sampler):
    """Yields `(index, epoch)` keys for this rank.

    Training (`shuffle=True`): a permutation seeded by (seed, epoch), padded to a multiple of the world size by
    repeating its head (as DistributedSampler does), then strided over ranks. Validation (`shuffle=False`): the
    dataset order strided over ranks without padding, so every sample is seen exactly once.
    """

    def __init__(self, length: int, shuffle: bool, seed: int = 0, rank: int = 0, world_size: int = 1):
        if length <= 0:
            raise ValueError("EpochSampler got an empty dataset")
        self.length, self.shuffle, self.seed = length, shuffle, seed
        self.rank, self.world_size = rank, world_size
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _indices(self) -> list[int]:
        if not self.shuffle:
            return list(range(self.length))[self.rank :: self.world_size]
        g = torch.Generator().manual_seed(int(np.random.SeedSequence([self.seed, self.epoch]).generate_state(1)[0]))
        order = torch.randperm(self.length, generator=g).tolist()
        total = -(-self.length // self.world_size) * self.world_size
        order += order[: total - self.length]
        return order[self.rank :: self.world_size]

    def __iter__(self):
        return iter([(i, self.epoch) for i in self._indices()])

    def __len__(self) -> int:
        return len(self._indices())


def split_key(key) -> tuple[int, int]:
    """A dataset key is an int or an (index, epoch) pair; return (index, epoch)."""
    if isinstance(key, (tuple, list)):
        return int(key[0]), int(key[1])
    return int(key), 0


def item_rng(seed: int, key) -> np.random.Generator:
    """The augmentation RNG of one sample in one epoch: independent of workers, ranks and resumes."""
    index, epoch = split_key(key)
    return np.random.default_rng((seed, epoch, index))
