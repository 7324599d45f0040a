"""sampler=one_per_place: one pair of each place per epoch, no place twice in a batch, seeded."""

from __future__ import annotations

import numpy as np
import pytest
from geoloc import registry


def sampler(labels, batch_size=4, seed=0, rank=0, world_size=1):
    return registry.build("sampler", {"name": "one_per_place"}, labels=np.asarray(labels), batch_size=batch_size,
                          seed=seed, rank=rank, world_size=world_size, neighbours=None)


def epoch_pairs(s, epoch):
    s.set_epoch(epoch)
    return [[i for i, e in b if e == epoch] for b in s]


def test_each_place_is_drawn_once_per_epoch_and_its_pairs_take_turns():
    labels = np.repeat(np.arange(12), 5)  # 12 places of 5 pairs each
    s = sampler(labels)
    seen = set()
    for epoch in range(6):
        batches = epoch_pairs(s, epoch)
        assert len(batches) == 3 and all(len(b) == 4 for b in batches)
        flat = [i for b in batches for i in b]
        assert sorted(labels[flat].tolist()) == list(range(12))  # every place once
        seen.update(flat)
    assert len(seen) > 12 * 2  # different pairs of a place in different epochs


def test_the_draw_is_seeded_and_the_tail_is_dropped():
    labels = np.repeat(np.arange(10), 3)
    assert epoch_pairs(sampler(labels), 2) == epoch_pairs(sampler(labels), 2)
    assert epoch_pairs(sampler(labels), 2) != epoch_pairs(sampler(labels, seed=1), 2)
    assert [len(b) for b in epoch_pairs(sampler(labels), 0)] == [4, 4]  # 10 places: 2 full batches of 4


def test_ranks_split_each_global_batch():
    labels = np.repeat(np.arange(16), 2)
    parts = [epoch_pairs(sampler(labels, batch_size=4, rank=r, world_size=2), 0) for r in range(2)]
    whole = epoch_pairs(sampler(labels, batch_size=8), 0)
    assert [a + b for a, b in zip(*parts)] == whole


def test_fewer_places_than_a_batch_is_refused():
    with pytest.raises(ValueError, match="distinct places"):
        sampler(np.repeat(np.arange(3), 4), batch_size=4)
