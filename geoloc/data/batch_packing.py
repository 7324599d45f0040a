"""One epoch's training pairs packed into global batches in which no place repeats (Sample4Geo's custom shuffle,
Deuser et al., ICCV 2023), optionally grown around anchors from their neighbour lists (GPS or similarity)."""
from __future__ import annotations

import numpy as np


def choose_neighbours(row: np.ndarray, select: int, search_range: int, rng: np.random.Generator) -> np.ndarray:
    """The neighbours an anchor pulls into its batch, from the first `search_range` entries of its list (nearest
    first, -1 = none): the nearest select // 2 always, and select - select // 2 drawn at random from the others,
    so batches are hard but not the same every epoch (Sample4Geo takes half nearest, half random)."""
    near = row[:search_range]
    near = near[near >= 0]
    always = select // 2
    others = near[always:]
    drawn = rng.choice(others, size=min(select - always, len(others)), replace=False) if len(others) else others
    return np.concatenate([near[:always], drawn])


def pack_batches(order: np.ndarray, place: np.ndarray, size: int, rng: np.random.Generator,
                 neighbours: np.ndarray | None = None, select: int = 0, search_range: int = 0) -> list[np.ndarray]:
    """Full batches of `size` pair indices, each pair at most once, no place twice in a batch; the tail that
    cannot fill a batch is dropped.

    order: (N,) this epoch's permutation of the pairs; place: (N,) place index (0..P-1) of each pair.
    Anchors are taken in `order`. A pair whose place is already in the batch waits, and the waiting pairs are
    tried first for the next batch. With `neighbours` (N, k), each anchor then pulls in
    choose_neighbours(neighbours[anchor], select, search_range, rng); a neighbour stands for its place: the pair
    itself when still unused, else that place's next unused pair in `order`.
    """
    n = len(order)
    place_of = place.tolist()
    used = [False] * n
    # each place's pairs in epoch order, with a cursor past the used ones, for standing in for a used neighbour
    by_place = order[np.argsort(place[order], kind="stable")].tolist()
    first = np.searchsorted(place[by_place], np.arange(int(place.max()) + 2)).tolist()
    cursor = first[:-1]

    def unused_pair_of(p: int) -> int:
        while cursor[p] < first[p + 1] and used[by_place[cursor[p]]]:
            cursor[p] += 1
        return by_place[cursor[p]] if cursor[p] < first[p + 1] else -1

    batches: list[np.ndarray] = []
    remaining = iter(order.tolist())
    waiting: list[int] = []
    while True:
        batch: list[int] = []
        places: set[int] = set()
        deferred: list[int] = []

        def add(i: int) -> None:
            used[i] = True
            batch.append(i)
            places.add(place_of[i])

        def offer(anchor: int) -> None:
            if used[anchor]:
                return
            if place_of[anchor] in places:
                deferred.append(anchor)
                return
            add(anchor)
            if neighbours is None:
                return
            for j in choose_neighbours(neighbours[anchor], select, search_range, rng).tolist():
                if len(batch) == size:
                    return
                if place_of[j] not in places:
                    stand_in = j if not used[j] else unused_pair_of(place_of[j])
                    if stand_in >= 0:
                        add(stand_in)

        for w, anchor in enumerate(waiting):
            if len(batch) == size:
                deferred.extend(waiting[w:])
                break
            offer(anchor)
        while len(batch) < size:
            anchor = next(remaining, None)
            if anchor is None:
                break
            offer(anchor)
        if len(batch) < size:
            return batches
        batches.append(np.asarray(batch, dtype=np.int64))
        waiting = deferred
