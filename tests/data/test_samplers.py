"""Training batch samplers: the default is the old batching exactly; the hard samplers never repeat a place in a
global batch, are deterministic per (seed, epoch), split batches over ranks, and group neighbours."""
import numpy as np
import pytest
import torch
from geoloc.data import samplers
from geoloc.data.batch_packing import choose_neighbours, pack_batches
from geoloc.data.neighbours import gps_neighbour_lists
from geoloc.engine.sampling import EpochSampler
from torch.utils.data import BatchSampler, DataLoader, Dataset

NAMES = ("shuffle", "no_duplicate", "gps_neighbours", "similarity")


def build(name, labels, batch_size=8, seed=0, rank=0, world_size=1, neighbours=None, **config):
    return getattr(samplers, name)(labels=labels, batch_size=batch_size, seed=seed, rank=rank,
                                   world_size=world_size, neighbours=neighbours, **config)


def world(name, labels, world_size, **kw):
    return [build(name, labels, rank=r, world_size=world_size, **kw) for r in range(world_size)]


def line_positions(n):
    """n pairs 10 m apart along a parallel, so pair i's GPS neighbours are i +- 1, i +- 2, ..."""
    return np.stack([np.full(n, 45.0), 7.0 + np.arange(n) * 10 / 78_710], 1)


def test_every_sampler_is_registered():
    from geoloc import registry

    for name in NAMES:
        assert registry._registry["sampler"][name] is getattr(samplers, name)


@pytest.mark.parametrize("world_size", [1, 2, 3])
@pytest.mark.parametrize("n,batch_size", [(1, 4), (5, 4), (37, 4), (64, 8), (100, 32), (9, 5), (7, 1)])
def test_shuffle_is_the_old_batching_exactly(n, batch_size, world_size):
    labels = np.arange(n)
    for rank in range(world_size):
        sampler = build("shuffle", labels, batch_size, seed=3, rank=rank, world_size=world_size)
        for epoch in range(3):
            keys = EpochSampler(n, shuffle=True, seed=3, rank=rank, world_size=world_size)
            keys.set_epoch(epoch)
            sampler.set_epoch(epoch)
            old = list(BatchSampler(keys, batch_size, drop_last=len(keys) >= 2 * batch_size))
            assert list(sampler) == old and len(sampler) == len(old)
        assert sampler.needs_descriptors is False


def hard_samplers(labels, world_size, batch_size=8, seed=0):
    """Each hard sampler on the same data: GPS lists from positions on a line, descriptors from a random net."""
    n = len(labels)
    neighbours = gps_neighbour_lists(line_positions(n), 16, labels)
    out = {"no_duplicate": world("no_duplicate", labels, world_size, batch_size=batch_size, seed=seed),
           "gps_neighbours": world("gps_neighbours", labels, world_size, batch_size=batch_size, seed=seed,
                                   neighbours=neighbours)}
    similar = world("similarity", labels, world_size, batch_size=batch_size, seed=seed, neighbours=neighbours)
    descriptors = np.random.default_rng(7).normal(size=(n, 8))
    for sampler in similar:
        sampler.set_descriptors(descriptors, descriptors[::-1].copy())
    out["similarity"] = similar
    return out


@pytest.mark.parametrize("world_size", [1, 2, 3])
def test_hard_batches_never_repeat_a_place_and_split_over_ranks(world_size):
    labels = np.random.default_rng(0).integers(0, 300, 400)  # some places have several pairs
    for name, ranks in hard_samplers(labels, world_size).items():
        for epoch in (0, 1):
            for sampler in ranks:
                sampler.set_epoch(epoch)
            per_rank = [list(sampler) for sampler in ranks]
            assert len({len(batches) for batches in per_rank}) == 1 and len(per_rank[0]) == len(ranks[0]) > 0
            seen = []
            for global_batch, shares in zip(ranks[0].batches(), zip(*per_rank)):
                assert all(len(share) == 8 for share in shares), name
                gathered = [i for share in shares for i, _ in share]
                assert gathered == global_batch.tolist(), name  # rank r holds slice r of the global batch
                assert len(set(labels[gathered])) == len(gathered), name
                assert {e for share in shares for _, e in share} == {epoch}
                seen += gathered
            assert len(seen) == len(set(seen)), f"{name}: a pair twice in one epoch"


def test_hard_batches_depend_on_seed_and_epoch_only():
    labels = np.arange(200)
    for name, (sampler,) in hard_samplers(labels, 1).items():
        again = hard_samplers(labels, 1)[name][0]
        other_seed = hard_samplers(labels, 1, seed=1)[name][0]
        first = list(sampler)
        assert list(again) == first and list(sampler) == first, name
        assert list(other_seed) != first, name
        sampler.set_epoch(1)
        assert [[i for i, _ in b] for b in sampler] != [[i for i, _ in b] for b in first], name


def reference_no_duplicate(order, labels, size):
    """An independent, quadratic version of the no-duplicate packing: skipped pairs go first into the next batch."""
    pending, batches = list(order), []
    while True:
        batch, places, rest = [], set(), []
        for i in pending:
            if len(batch) < size and labels[i] not in places:
                batch.append(i)
                places.add(labels[i])
            else:
                rest.append(i)
        if len(batch) < size:
            return batches
        batches.append(batch)
        pending = rest


@pytest.mark.parametrize("places,size", [(100, 8), (30, 8), (12, 10), (300, 16)])
def test_no_duplicate_packing_equals_a_brute_force_version(places, size):
    rng = np.random.default_rng(places)
    labels = rng.integers(0, places, 300)
    order = rng.permutation(300)
    got = pack_batches(order, np.unique(labels, return_inverse=True)[1].reshape(-1), size, rng)
    assert [b.tolist() for b in got] == reference_no_duplicate(order, labels, size)


def test_a_used_neighbour_is_stood_in_for_by_its_place_s_next_unused_pair():
    place = np.array([0, 0, 1, 2, 3, 4, 0])  # pairs 0, 1 and 6 show one place
    neighbours = np.full((7, 1), -1)
    neighbours[0], neighbours[3] = 2, 0
    order = np.array([0, 3, 4, 5, 6, 1, 2])
    got = pack_batches(order, place, 2, np.random.default_rng(0), neighbours, select=1, search_range=1)
    # 3's neighbour 0 is taken, so place 0's next unused pair in the epoch's order (6, not 1) joins 3
    assert [b.tolist() for b in got] == [[0, 2], [3, 6], [4, 5]]


def test_no_duplicate_on_one_to_one_data_uses_all_but_the_tail():
    sampler = build("no_duplicate", np.arange(100), batch_size=4, world_size=2)
    used = [i for batch in sampler.batches() for i in batch.tolist()]
    assert len(sampler) == 12 and len(set(used)) == 96


def share_of_batchmates_near(batches, neighbours, search_range):
    """The share of pairs that have a batch-mate among the first search_range entries of their list."""
    hits = [len(set(neighbours[i, :search_range]) & set(batch.tolist())) > 0 for batch in batches for i in batch]
    return float(np.mean(hits))


def test_gps_batches_hold_neighbours_far_more_often_than_random_batches():
    n, size, search_range = 1000, 32, 16
    neighbours = gps_neighbour_lists(line_positions(n), 32)
    gps = build("gps_neighbours", np.arange(n), batch_size=size, neighbours=neighbours,
                neighbour_select=8, neighbour_range=search_range)
    plain = build("no_duplicate", np.arange(n), batch_size=size)
    # a random batch-mate is among 16 listed pairs with chance ~16/1000: 1 - (1 - 0.016)^31 ~ 0.39
    assert share_of_batchmates_near(plain.batches(), neighbours, search_range) < 0.55
    assert share_of_batchmates_near(gps.batches(), neighbours, search_range) > 0.95


def grouped_lists(groups, members, rng):
    """Row i: the other members of i's group (shuffled), then as many pairs from other groups."""
    n = groups * members
    rows = []
    for i in range(n):
        group = i // members
        mates = [j for j in range(group * members, (group + 1) * members) if j != i]
        strangers = [j for j in rng.permutation(n) if j // members != group][:members - 1]
        rows.append(list(rng.permutation(mates)) + strangers)
    return np.array(rows)


def test_gps_batches_take_neighbours_only_from_the_first_neighbour_range():
    groups, members = 32, 8
    neighbours = grouped_lists(groups, members, np.random.default_rng(0))
    sampler = build("gps_neighbours", np.arange(groups * members), batch_size=16, world_size=2,
                    neighbours=neighbours, neighbour_select=members - 1, neighbour_range=members - 1)
    for epoch in range(3):
        sampler.set_epoch(epoch)
        assert len(sampler) == groups * members // 32
        for batch in sampler.batches():  # an anchor brings its whole group and nobody from beyond the range
            assert (np.bincount(batch // members, minlength=groups) % members == 0).all()


def test_choose_neighbours_keeps_the_nearest_half_and_draws_the_rest_within_range():
    row = np.array([5, 9, -1, 3, 7, 2, 8, 4, 1, 6])
    rng = np.random.default_rng(0)
    drawn = set()
    for _ in range(200):
        chosen = choose_neighbours(row, 4, 8, rng).tolist()
        assert len(chosen) == len(set(chosen)) == 4 and chosen[:2] == [5, 9]
        assert set(chosen[2:]) <= {3, 7, 2, 8, 4}  # within the first 8 entries, -1 skipped
        drawn |= set(chosen[2:])
    assert drawn == {3, 7, 2, 8, 4}
    assert choose_neighbours(row, 3, 3, rng).tolist() == [5, 9]  # only two listed in range


def clustered_descriptors(clusters, members, dim=32, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(clusters, dim))
    points = np.repeat(centres, members, 0) + 0.05 * rng.normal(size=(clusters * members, dim))
    return torch.nn.functional.normalize(torch.from_numpy(points).float(), dim=1)


def test_similarity_batches_group_pairs_with_similar_descriptors():
    clusters, members = 64, 4
    labels = np.arange(clusters * members)
    sampler = build("similarity", labels, batch_size=16, neighbour_select=members - 1,
                    neighbour_range=members - 1)
    assert sampler.needs_descriptors is True
    descriptors = clustered_descriptors(clusters, members)
    perm = np.random.default_rng(1).permutation(len(labels))  # dataset order unrelated to the clusters
    descriptors, cluster = descriptors[perm], perm // members
    sampler.set_descriptors(descriptors, descriptors)
    for epoch in range(2):
        sampler.set_epoch(epoch)
        for batch in sampler.batches():  # each anchor brings its 3 cluster mates: whole clusters only
            assert (np.bincount(cluster[batch], minlength=clusters) % members == 0).all()


def test_similarity_ranks_references_against_queries():
    reference = torch.nn.functional.normalize(torch.randn(90, 32, generator=torch.Generator().manual_seed(0)), dim=1)
    following = torch.arange(90) // 3 * 3 + (torch.arange(90) + 1) % 3  # 0 -> 1 -> 2 -> 0, 3 -> 4 -> 5 -> 3...
    # query i looks like the reference of the pair after it in its triple, and like no other
    sampler = build("similarity", np.arange(90), batch_size=2, neighbour_select=1, neighbour_range=1)
    sampler.set_descriptors(reference[following], reference)
    pulled = [int(b) == following[a] for a, b in sampler.batches()]  # an anchor, then its neighbour if unused
    assert np.mean(pulled) > 0.5  # a random second pair is the anchor's follower with chance 1/89


def test_similarity_falls_back_to_gps_then_to_no_duplicate_before_descriptors():
    labels = np.random.default_rng(0).integers(0, 250, 300)
    neighbours = gps_neighbour_lists(line_positions(300), 16, labels)
    for given, twin in ((neighbours, "gps_neighbours"), (None, "no_duplicate")):
        config = {} if given is None else {"neighbour_select": 8, "neighbour_range": 16}
        sampler = build("similarity", labels, neighbours=given)
        fallback = build(twin, labels, neighbours=given, **config)
        for epoch in (0, 1):
            sampler.set_epoch(epoch)
            fallback.set_epoch(epoch)
            assert list(sampler) == list(fallback)
        descriptors = np.random.default_rng(1).normal(size=(300, 8))
        sampler.set_descriptors(descriptors, descriptors)
        assert list(sampler) != list(fallback)


class Keys(Dataset):
    def __init__(self, n):
        self.n = n

    def __len__(self):
        return self.n

    def __getitem__(self, key):
        index, epoch = key
        return {"index": index, "epoch": epoch}


@pytest.mark.parametrize("name", NAMES)
def test_a_dataloader_runs_each_sampler(name):
    labels = np.arange(40)
    neighbours = gps_neighbour_lists(line_positions(40), 16)
    sampler = build(name, labels, batch_size=4, rank=1, world_size=2, neighbours=neighbours)
    sampler.set_epoch(2)
    if sampler.needs_descriptors:
        sampler.set_descriptors(torch.randn(40, 8), torch.randn(40, 8))
    loaded = list(DataLoader(Keys(40), batch_sampler=sampler, num_workers=0))
    expected = list(sampler)
    assert len(loaded) == len(expected) == len(sampler) > 0
    for batch, keys in zip(loaded, expected):
        assert batch["index"].tolist() == [i for i, _ in keys] and set(batch["epoch"].tolist()) == {2}


@pytest.mark.parametrize("name", ["no_duplicate", "gps_neighbours", "similarity"])
def test_too_little_data_for_one_global_batch_is_refused(name):
    neighbours = gps_neighbour_lists(line_positions(12), 16)
    with pytest.raises(ValueError, match="12 pairs, fewer than one global batch.*8 x 2 ranks = 16"):
        build(name, np.arange(12), batch_size=8, world_size=2, neighbours=neighbours)
    with pytest.raises(ValueError, match="only 5 distinct places.*batch of 8 pairs"):
        build(name, np.arange(20) % 5, batch_size=8, neighbours=gps_neighbour_lists(line_positions(20), 16))


def test_bad_configuration_gets_a_clear_error():
    labels = np.arange(40)
    with pytest.raises(ValueError, match="no GPS positions; use sampler.name= shuffle, no_duplicate or similarity"):
        build("gps_neighbours", labels)
    table = gps_neighbour_lists(line_positions(40), 8)
    with pytest.raises(ValueError, match="neighbour_select=9 exceeds sampler.neighbour_range=8"):
        build("gps_neighbours", labels, neighbours=table, neighbour_select=9, neighbour_range=8)
    with pytest.raises(ValueError, match="neighbour_range=16 .* exceeds the 8 neighbours"):
        build("similarity", labels, neighbours=table)
    with pytest.raises(ValueError, match="outside \\[-1, 40\\)"):
        build("gps_neighbours", labels, neighbours=table + 1, neighbour_select=2, neighbour_range=8)
    with pytest.raises(ValueError, match="\\(40, k\\) integer array"):
        build("gps_neighbours", labels, neighbours=table[:5], neighbour_select=2, neighbour_range=8)
    with pytest.raises(ValueError, match="neighbour_select must be an integer >= 1"):
        build("similarity", labels, neighbour_select=0)
    with pytest.raises(ValueError, match="labels must be a non-empty \\(N,\\) integer array"):
        build("no_duplicate", labels.astype(float))
    with pytest.raises(ValueError, match="rank 2 is outside world_size 2"):
        build("shuffle", labels, rank=2, world_size=2)
    sampler = build("similarity", labels)
    with pytest.raises(ValueError, match="one query and one reference descriptor per training pair \\(40\\)"):
        sampler.set_descriptors(np.zeros((39, 4)), np.zeros((39, 4)))


def test_the_pool_deals_every_place_once_before_any_comes_back():
    """A brute-force reading of the deal: within each run of epochs_per_deal epochs no place repeats (nor within
    an epoch), each epoch holds places_per_epoch places, one pair of each, and the batches cover them in order."""
    labels = np.repeat(np.arange(50), 2)  # 50 places of two pairs each
    sampler = build("pool", labels, batch_size=4, places_per_epoch=12)
    assert sampler.epochs_per_deal == 4  # 48 of the 50 places a deal; 2 wait for another deal
    seen_per_deal: dict[int, list[int]] = {}
    for epoch in range(12):
        sampler.set_epoch(epoch)
        keys = [key for batch in sampler for key in batch]
        assert {e for _, e in keys} == {epoch} and len(keys) == 12
        places = [int(labels[i]) for i, _ in keys]
        assert places == sampler.places_of(epoch).tolist() and len(set(places)) == 12
        seen_per_deal.setdefault(epoch // 4, []).extend(places)
    for places in seen_per_deal.values():
        assert len(places) == len(set(places)) == 48
    assert len({tuple(sorted(p)) for p in seen_per_deal.values()}) == 3  # each deal leaves out other places
    sampler.set_epoch(1)
    again = build("pool", labels, batch_size=4, places_per_epoch=12)
    again.set_epoch(1)
    assert list(again) == list(sampler)  # (seed, epoch) alone
    other_seed = build("pool", labels, batch_size=4, places_per_epoch=12, seed=1)
    other_seed.set_epoch(1)
    assert list(other_seed) != list(sampler)


def test_the_pool_splits_each_global_batch_over_ranks_and_refuses_a_bad_size():
    labels = np.arange(64)
    ranks = world("pool", labels, 2, batch_size=4, places_per_epoch=20)
    for r in ranks:
        r.set_epoch(3)
    per_rank = [list(r) for r in ranks]
    assert len(per_rank[0]) == len(per_rank[1]) == 2  # 20 places: two global batches of 8, the rest dropped
    together = [i for b0, b1 in zip(*per_rank) for i, _ in b0 + b1]
    assert together == ranks[0].places_of(3)[:16].tolist()
    for bad in (7, 65, 12.0, True):
        with pytest.raises(ValueError, match="sampler.places_per_epoch must be an integer from one global batch"):
            build("pool", labels, batch_size=4, world_size=2, places_per_epoch=bad)
