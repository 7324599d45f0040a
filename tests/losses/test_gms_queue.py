"""GMSQueue: FIFO order, masking, hardest negatives, checkpoint round trip, size 0 (docs/conventions.md "GMS queue")."""
import io

import pytest
import torch
import torch.nn.functional as F
from geoloc.losses import GMSQueue, soft_margin_triplet

from helpers.brute_force import brute_hardest


def entries(ids, dim=3):
    """Descriptors whose first coordinate carries the id, so the queue's content is readable."""
    ids = torch.as_tensor(ids, dtype=torch.long)
    desc = torch.zeros(len(ids), dim)
    desc[:, 0] = ids.float()
    return desc, ids


def test_starts_empty():
    queue = GMSQueue(4, 3)
    assert len(queue) == 0 and int(queue.ptr) == 0
    assert queue.ids.tolist() == [-1] * 4 and queue.ids.dtype == torch.long
    assert queue.ptr.dtype == torch.long and queue.descriptors.dtype == torch.float32
    assert GMSQueue(2, 1, dtype=torch.float64).descriptors.dtype == torch.float64  # dim 1 is a valid size
    _, mask = queue.negatives(torch.tensor([1, 2]))
    assert mask.shape == (2, 4) and not mask.any()


def test_location_id_zero_is_a_filled_slot():
    queue = GMSQueue(4, 3)
    queue.push(*entries([0, 1]))
    assert len(queue) == 2
    _, mask = queue.negatives(torch.tensor([1]))
    assert mask.tolist() == [[True, False, False, False]]


def test_fifo_order_and_wrap_around():
    queue = GMSQueue(5, 3)
    queue.push(*entries([10, 11, 12]))
    assert queue.ids.tolist() == [10, 11, 12, -1, -1] and int(queue.ptr) == 3
    queue.push(*entries([13, 14, 15]))  # wraps: 15 overwrites the oldest (10)
    assert queue.ids.tolist() == [15, 11, 12, 13, 14] and int(queue.ptr) == 1
    assert queue.descriptors[:, 0].tolist() == [15, 11, 12, 13, 14]
    assert len(queue) == 5


def test_push_larger_than_queue_equals_one_by_one():
    big, single = GMSQueue(4, 3), GMSQueue(4, 3)
    big.push(*entries([1]))
    single.push(*entries([1]))
    ids = list(range(20, 31))
    big.push(*entries(ids))
    for i in ids:
        single.push(*entries([i]))
    assert big.ids.tolist() == single.ids.tolist()
    assert int(big.ptr) == int(single.ptr)
    torch.testing.assert_close(big.descriptors, single.descriptors)


def test_push_is_detached_and_cast():
    queue = GMSQueue(3, 2)
    desc = torch.ones(2, 2, dtype=torch.float64, requires_grad=True)
    queue.push(desc * 2, torch.tensor([4, 5], dtype=torch.int32))
    assert not queue.descriptors.requires_grad and queue.descriptors.dtype == torch.float32
    assert queue.ids.dtype == torch.long and queue.ids.tolist() == [4, 5, -1]


def test_mask_drops_empty_slots_and_same_location():
    queue = GMSQueue(5, 3)
    queue.push(*entries([7, 8, 7]))
    desc, mask = queue.negatives(torch.tensor([7, 8, 9]))
    assert desc.shape == (5, 3)
    assert mask.tolist() == [
        [False, True, False, False, False],
        [True, False, True, False, False],
        [True, True, True, False, False],
    ]


def test_hardest_negatives_match_brute_force():
    g = torch.Generator().manual_seed(0)
    query = F.normalize(torch.randn(8, 6, generator=g), dim=1)
    reference = F.normalize(torch.randn(8, 6, generator=g), dim=1)
    reference[4] = query[3]  # the closest reference to query 3 shares its location: not its negative
    ids = torch.tensor([0, 1, 2, 3, 3, 5, 6, 7])
    desc, neg_ids = GMSQueue.hardest_negatives(query, reference.requires_grad_(), ids)
    expected = brute_hardest(query, reference.detach(), ids)
    assert len(expected) == 8 and expected[3] != 4
    assert neg_ids.tolist() == ids[expected].tolist()
    torch.testing.assert_close(desc, reference.detach()[expected])
    assert not desc.requires_grad


def test_hardest_negatives_without_negative_are_skipped_by_push():
    q = F.normalize(torch.randn(3, 4), dim=1)
    desc, ids = GMSQueue.hardest_negatives(q, q, torch.tensor([5, 5, 6]))
    assert ids.tolist() == [6, 6, 5]
    desc, ids = GMSQueue.hardest_negatives(q, q, torch.tensor([5, 5, 5]))  # one row per query, none valid
    assert desc.shape == (3, 4) and ids.tolist() == [-1, -1, -1] and not desc.any()
    queue = GMSQueue(4, 4)
    queue.push(*entries([1], dim=4))
    queue.push(desc, ids)
    assert queue.ids.tolist() == [1, -1, -1, -1] and int(queue.ptr) == 1


def test_queue_negatives_feed_the_loss():
    g = torch.Generator().manual_seed(1)
    q = F.normalize(torch.randn(4, 6, generator=g), dim=1)
    r = F.normalize(torch.randn(4, 6, generator=g), dim=1)
    queue = GMSQueue(6, 6)
    queue.push(*GMSQueue.hardest_negatives(q, r, torch.arange(4)))
    extra, mask = queue.negatives(torch.arange(4))
    loss = soft_margin_triplet(q, r, extra_negatives=extra, extra_mask=mask)
    kept = mask.sum().item()
    assert 0 < kept < 4 * 6
    # Recompute with only the kept (query, negative) pairs, one at a time.
    d_pos = 2 - 2 * (q * r).sum(1)
    terms = [F.softplus(10 * (d_pos[i] - (2 - 2 * q[i] @ extra[k]))) for i in range(4) for k in range(6) if mask[i, k]]
    in_batch = soft_margin_triplet(q, r) * 2 * 4 * 3
    torch.testing.assert_close(loss, (in_batch + torch.stack(terms).sum()) / (24 + kept))


def test_state_dict_round_trip_restores_queue():
    queue = GMSQueue(4, 3)
    queue.push(*entries([1, 2, 3, 4, 5]))
    buf = io.BytesIO()
    torch.save(queue.state_dict(), buf)
    buf.seek(0)
    restored = GMSQueue(4, 3)
    restored.load_state_dict(torch.load(buf, weights_only=True))
    assert restored.ids.tolist() == queue.ids.tolist() and int(restored.ptr) == int(queue.ptr) == 1
    torch.testing.assert_close(restored.descriptors, queue.descriptors)
    restored.push(*entries([6]))
    queue.push(*entries([6]))
    assert restored.ids.tolist() == queue.ids.tolist() == [5, 6, 3, 4]
    assert set(queue.state_dict()) == {"descriptors", "ids", "ptr"}


def test_size_zero_is_disabled():
    queue = GMSQueue(0, 3)
    assert not queue.enabled
    assert queue.negatives(torch.tensor([1, 2])) == (None, None)
    before = {k: v.clone() for k, v in queue.state_dict().items()}
    queue.push(*entries([1, 2]))  # a disabled queue ignores pushes: no error, nothing stored
    after = queue.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert len(queue) == 0 and queue.descriptors.shape == (0, 3) and int(queue.ptr) == 0
    q = F.normalize(torch.randn(3, 3), dim=1)
    extra, mask = queue.negatives(torch.arange(3))
    torch.testing.assert_close(soft_margin_triplet(q, q, extra_negatives=extra, extra_mask=mask),
                               soft_margin_triplet(q, q))


def test_bad_inputs():
    with pytest.raises(ValueError, match="size >= 0"):
        GMSQueue(-1, 3)
    with pytest.raises(ValueError, match="dim > 0"):
        GMSQueue(3, 0)
    queue = GMSQueue(3, 4)
    with pytest.raises(ValueError, match="N x 4"):
        queue.push(torch.zeros(2, 3), torch.tensor([1, 2]))
    with pytest.raises(ValueError, match="N ids"):
        queue.push(torch.zeros(2, 4), torch.tensor([1, 2, 3]))


def _push_on_rank(rank, world, init_file, result_file):
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        queue = GMSQueue(5, 3)
        queue.push(*entries([[10, 11], [20]][rank]))  # ranks push different numbers of entries
        torch.save({"ids": queue.ids, "ptr": queue.ptr, "descriptors": queue.descriptors}, f"{result_file}.{rank}")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_push_gathers_over_ranks(tmp_path):
    import torch.multiprocessing as mp

    mp.spawn(_push_on_rank, args=(2, tmp_path / "init", tmp_path / "out"), nprocs=2)
    states = [torch.load(f"{tmp_path / 'out'}.{r}", weights_only=True) for r in range(2)]
    for state in states:  # every rank holds the same queue, in rank order
        assert state["ids"].tolist() == [10, 11, 20, -1, -1] and int(state["ptr"]) == 3
    torch.testing.assert_close(states[0]["descriptors"], states[1]["descriptors"])
