"""Training batch samplers, chosen by `sampler.name` (docs/samplers.md). This module declares the `sampler` kind
and registers the built-ins below.

The trainer calls a factory as factory(labels=, batch_size=, seed=, rank=, world_size=, neighbours=, **config)
and hands the result to DataLoader(batch_sampler=...). A sampler yields, per batch, this rank's list of
`(index, epoch)` keys (as EpochSampler does, so augmentation stays reproducible). labels: (N,) the place of each
training pair; neighbours: (N, k) GPS neighbour lists (geoloc.data.neighbours) or None.

- shuffle: the old batching, exactly (EpochSampler + BatchSampler).
- pool: a training set far larger than an epoch, dealt places_per_epoch places at a time.
- no_duplicate, gps_neighbours, similarity: every rank packs the same global batches of batch_size x
  world_size pairs from (seed, epoch) and takes slice [rank * batch_size, (rank + 1) * batch_size) of each, so
  the batch the loss gathers over ranks (rank order) is the packed one, with no place twice in it.
"""
from __future__ import annotations

import numpy as np
from torch.utils.data import BatchSampler

from geoloc.data.batch_packing import pack_batches
from geoloc.data.neighbours import descriptor_neighbour_lists
from geoloc.registry import declare, register

declare("sampler", section="sampler",
        runtime=("labels", "batch_size", "seed", "rank", "world_size", "neighbours"))

SAMPLERS_WITHOUT_GPS = "shuffle, no_duplicate or similarity"


class ShuffleBatches:
    """EpochSampler(N, shuffle=True) keys in batches of batch_size, the last incomplete one dropped when this
    rank has at least two batches' worth: exactly the trainer's batching before samplers were configurable."""

    needs_descriptors = False

    def __init__(self, length: int, batch_size: int, seed: int, rank: int, world_size: int):
        # imported here: geoloc.engine's package imports the trainer, which builds samplers from this module
        from geoloc.engine.sampling import EpochSampler

        self.keys = EpochSampler(length, shuffle=True, seed=seed, rank=rank, world_size=world_size)
        self.batch_size = batch_size
        self.drop_last = len(self.keys) >= 2 * batch_size

    def set_epoch(self, epoch: int) -> None:
        self.keys.set_epoch(epoch)

    def __iter__(self):
        return iter(BatchSampler(self.keys, self.batch_size, self.drop_last))

    def __len__(self) -> int:
        return len(BatchSampler(self.keys, self.batch_size, self.drop_last))


class PlaceBatches:
    """Global batches without a repeated place, grown from `neighbours` (N, k) when given (Sample4Geo's shuffle
    with GPS neighbours; batch_packing.pack_batches). Deterministic in (seed, epoch); built once per epoch."""

    needs_descriptors = False

    def __init__(self, name: str, labels, batch_size: int, seed: int, rank: int, world_size: int,
                 neighbours=None, neighbour_select: int = 0, neighbour_range: int = 0):
        self.name, self.seed, self.epoch = name, seed, 0
        self.labels = _check_labels(name, labels)
        self.batch_size, self.rank, self.world_size = _check_ranks(name, batch_size, rank, world_size)
        self.global_size = batch_size * world_size
        _, self.place = np.unique(self.labels, return_inverse=True)
        self.place = self.place.reshape(-1)
        places, n = int(self.place.max()) + 1, len(self.labels)
        if n < self.global_size:
            raise ValueError(f"sampler.name={name}: the training set has {n} pairs, fewer than one global batch "
                             f"(dataset.batch_size {batch_size} x {world_size} ranks = {self.global_size}); lower "
                             f"dataset.batch_size or train on more data")
        if places < self.global_size:
            raise ValueError(f"sampler.name={name}: the training pairs show only {places} distinct places, so no "
                             f"batch of {self.global_size} pairs (dataset.batch_size {batch_size} x {world_size} "
                             f"ranks) can avoid repeating one; lower dataset.batch_size or use sampler.name=shuffle")
        self.neighbours = None if neighbours is None else _check_neighbours(name, neighbours, n, neighbour_range)
        self.select, self.search_range = neighbour_select, neighbour_range
        self._packed: tuple | None = None

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def current_neighbours(self) -> np.ndarray | None:
        return self.neighbours

    def batches(self) -> list[np.ndarray]:
        """This epoch's global batches: arrays of batch_size x world_size pair indices."""
        table = self.current_neighbours()
        if self._packed is None or self._packed[0] != self.epoch or self._packed[1] is not table:
            rng = np.random.default_rng([self.seed, self.epoch])
            order = rng.permutation(len(self.labels))
            batches = pack_batches(order, self.place, self.global_size, rng, table, self.select, self.search_range)
            self._packed = (self.epoch, table, batches)
        return self._packed[2]

    def __iter__(self):
        epoch, start = self.epoch, self.rank * self.batch_size
        for batch in self.batches():
            yield [(i, epoch) for i in batch[start:start + self.batch_size].tolist()]

    def __len__(self) -> int:
        return len(self.batches())


class SimilarityBatches(PlaceBatches):
    """PlaceBatches grown from descriptor neighbours (Sample4Geo's similarity sampling): for each pair, the
    places whose reference descriptors best match its query descriptor, recomputed whenever the task calls
    set_descriptors (before each epoch). Until then it uses the GPS neighbours, or none (no_duplicate)."""

    needs_descriptors = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.similar: np.ndarray | None = None

    def set_descriptors(self, query, reference) -> None:
        """query, reference: (N, D) descriptors of the training pairs in dataset order, the same on every rank
        (gathered), since each rank packs the batches itself."""
        n = len(self.labels)
        if len(query) != n or len(reference) != n:
            raise ValueError(f"sampler.name={self.name}: set_descriptors needs one query and one reference "
                             f"descriptor per training pair ({n}), got {len(query)} and {len(reference)}")
        self.similar = descriptor_neighbour_lists(query, reference, self.labels, self.search_range)

    def current_neighbours(self) -> np.ndarray | None:
        return self.neighbours if self.similar is None else self.similar


class OnePerPlaceBatches(PlaceBatches):
    """Each epoch, one pair of every place drawn at random, the places in a seeded permutation cut into batches
    (no place twice, as each appears once): an epoch is one pass over the places, not over the pairs, and a
    place's views take turns from epoch to epoch (University-1652's baseline draws one drone view per building
    each time it sees the building). The incomplete last global batch is dropped. Deterministic in (seed, epoch)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        order = np.argsort(self.place, kind="stable")
        self.members = np.split(order, np.cumsum(np.bincount(self.place))[:-1])  # place -> its pair indices

    shuffle_drawn = True  # the drawn pairs are put in a seeded order (PoolBatches deals its places in one already)

    def epoch_places(self) -> np.ndarray:
        """The places this epoch trains on, in order: all of them."""
        return np.arange(len(self.members))

    def batches(self) -> list[np.ndarray]:
        if self._packed is None or self._packed[0] != self.epoch:
            rng = np.random.default_rng([self.seed, self.epoch])
            drawn = np.array([self.members[p][rng.integers(len(self.members[p]))] for p in self.epoch_places()])
            if self.shuffle_drawn:
                drawn = drawn[rng.permutation(len(drawn))]
            full = len(drawn) // self.global_size * self.global_size
            self._packed = (self.epoch, None, list(drawn[:full].reshape(-1, self.global_size)))
        return self._packed[2]


class PoolBatches(OnePerPlaceBatches):
    """A pool of places far larger than an epoch: each epoch trains on the next `places_per_epoch` places, one
    random pair of each, cut into batches. The places are dealt from seeded permutations of the whole pool, one
    after another, `places_per_epoch` at a time (the pool's last places_per_epoch-remainder of each permutation are
    left for a later one), so a place comes back only once every other has had its turn, and no place is twice in
    an epoch. The incomplete last global batch is dropped. Deterministic in (seed, epoch)."""

    def __init__(self, *args, places_per_epoch: int, **kwargs):
        super().__init__(*args, **kwargs)
        places = len(self.members)
        if isinstance(places_per_epoch, bool) or not isinstance(places_per_epoch, (int, np.integer)) or not (
                self.global_size <= places_per_epoch <= places):
            raise ValueError(f"sampler.places_per_epoch must be an integer from one global batch "
                             f"({self.global_size}) to the {places} places of the training set, got {places_per_epoch!r}")
        self.places_per_epoch = int(places_per_epoch)
        self.epochs_per_deal = places // self.places_per_epoch

    def places_of(self, epoch: int) -> np.ndarray:
        """The places epoch `epoch` trains on: slot epoch % epochs_per_deal of deal epoch // epochs_per_deal."""
        deal, slot = divmod(int(epoch), self.epochs_per_deal)
        order = np.random.default_rng([self.seed, 2**31, deal]).permutation(len(self.members))  # the deal's order
        return order[slot * self.places_per_epoch:(slot + 1) * self.places_per_epoch]

    shuffle_drawn = False

    def epoch_places(self) -> np.ndarray:
        return self.places_of(self.epoch)


@register("sampler", "shuffle")
def shuffle(labels, batch_size: int, seed: int, rank: int, world_size: int, neighbours=None) -> ShuffleBatches:
    """The default: the engine's seeded permutation per epoch (pairs of one place may share a batch)."""
    _check_ranks("shuffle", batch_size, rank, world_size)
    return ShuffleBatches(len(_check_labels("shuffle", labels)), batch_size, seed, rank, world_size)


@register("sampler", "no_duplicate")
def no_duplicate(labels, batch_size: int, seed: int, rank: int, world_size: int, neighbours=None) -> PlaceBatches:
    """A seeded permutation per epoch packed into batches without a repeated place."""
    return PlaceBatches("no_duplicate", labels, batch_size, seed, rank, world_size)


@register("sampler", "one_per_place")
def one_per_place(labels, batch_size: int, seed: int, rank: int, world_size: int,
                  neighbours=None) -> OnePerPlaceBatches:
    """One random pair of each place per epoch, the places shuffled into batches."""
    return OnePerPlaceBatches("one_per_place", labels, batch_size, seed, rank, world_size)


@register("sampler", "pool")
def pool(labels, batch_size: int, seed: int, rank: int, world_size: int, neighbours=None,
         places_per_epoch: int = 1200) -> PoolBatches:
    """places_per_epoch places of the pool each epoch, dealt so that a place comes back only after all the others."""
    return PoolBatches("pool", labels, batch_size, seed, rank, world_size, places_per_epoch=places_per_epoch)


@register("sampler", "gps_neighbours")
def gps_neighbours(labels, batch_size: int, seed: int, rank: int, world_size: int, neighbours=None,
                   neighbour_select: int = 8, neighbour_range: int = 16) -> PlaceBatches:
    """Batches grown from random anchors and neighbour_select of the first neighbour_range of their GPS
    neighbours."""
    if neighbours is None:
        raise ValueError(f"sampler.name=gps_neighbours needs GPS neighbour lists, but this dataset has no GPS "
                         f"positions; use sampler.name= {SAMPLERS_WITHOUT_GPS}")
    _check_selection("gps_neighbours", neighbour_select, neighbour_range)
    return PlaceBatches("gps_neighbours", labels, batch_size, seed, rank, world_size, neighbours,
                        neighbour_select, neighbour_range)


@register("sampler", "similarity")
def similarity(labels, batch_size: int, seed: int, rank: int, world_size: int, neighbours=None,
               neighbour_select: int = 8, neighbour_range: int = 16) -> SimilarityBatches:
    """Batches grown from random anchors and neighbour_select of the neighbour_range places most similar to
    them by descriptor, recomputed each epoch; GPS neighbours (or none) until descriptors are given."""
    _check_selection("similarity", neighbour_select, neighbour_range)
    return SimilarityBatches("similarity", labels, batch_size, seed, rank, world_size, neighbours,
                             neighbour_select, neighbour_range)


def _check_labels(name: str, labels) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.ndim != 1 or len(labels) == 0 or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"sampler.name={name}: labels must be a non-empty (N,) integer array, the place of each "
                         f"training pair; got {labels.dtype} of shape {labels.shape}")
    return labels


def _check_ranks(name: str, batch_size, rank, world_size) -> tuple[int, int, int]:
    for key, value, low in (("batch_size", batch_size, 1), ("world_size", world_size, 1), ("rank", rank, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"sampler.name={name}: {key} must be an integer >= {low}, got {value!r}")
    if rank >= world_size:
        raise ValueError(f"sampler.name={name}: rank {rank} is outside world_size {world_size}")
    return int(batch_size), int(rank), int(world_size)


def _check_selection(name: str, select, search_range) -> None:
    for key, value in (("neighbour_select", select), ("neighbour_range", search_range)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"sampler.{key} must be an integer >= 1 (sampler.name={name}), got {value!r}")
    if select > search_range:
        raise ValueError(f"sampler.neighbour_select={select} exceeds sampler.neighbour_range={search_range} "
                         f"(sampler.name={name}): it picks that many of the first neighbour_range neighbours")


def _check_neighbours(name: str, neighbours, n: int, search_range: int) -> np.ndarray:
    table = np.asarray(neighbours)
    if table.ndim != 2 or len(table) != n or not np.issubdtype(table.dtype, np.integer):
        raise ValueError(f"sampler.name={name}: the dataset's neighbour lists must be an ({n}, k) integer array "
                         f"(one row per training pair), got {table.dtype} of shape {table.shape}")
    if table.size and (table.min() < -1 or table.max() >= n):
        raise ValueError(f"sampler.name={name}: the dataset's neighbour lists hold indices outside [-1, {n}); "
                         f"recompute them with geoloc.data.neighbours.gps_neighbour_lists")
    if table.shape[1] < search_range:
        raise ValueError(f"sampler.neighbour_range={search_range} (sampler.name={name}) exceeds the {table.shape[1]} "
                         f"neighbours the dataset lists per pair; lower sampler.neighbour_range")
    return table.astype(np.int64, copy=False)
