"""The cross-view task's training loss is the formula of docs/conventions.md "Soft-margin triplet" and "GMS queue",
written out by hand: the configured alpha, the GMS queue filled after the loss with each query's hardest in-batch
negative, queue entries of the query's own location left out, and no queue before loss.queue_start_epoch."""
from types import SimpleNamespace

import torch
from geoloc.losses.gms_triplet_loss import GMSTripletLoss

import conftest
from helpers.brute_force import brute_force, brute_hardest

# Batch-norm trunk in train mode: at initialisation a plain tiny VGG maps every image to nearly one descriptor,
# where every term is log 2 whatever the formula; batch statistics spread the descriptors out.


def tiny_task(**loss):
    torch.manual_seed(0)
    return conftest.tiny_task(loss=loss)


def step(task, data, epoch):
    """One training step at `epoch`, as the trainer runs it: the epoch hook first."""
    task.on_train_epoch_start(SimpleNamespace(epoch=epoch))
    return task.training_step(data, SimpleNamespace(epoch=epoch))


def batch(ids, seed):
    g = torch.Generator().manual_seed(seed)
    return {"query": torch.randn(len(ids), 3, 32, 32, generator=g),
            "reference": torch.randn(len(ids), 3, 32, 32, generator=g), "index": torch.tensor(ids),
            "label": torch.tensor(ids)}


def descriptors(task, data):
    """What training_step sees: train-mode batch statistics depend on the batch only, so a second pass agrees."""
    with torch.no_grad():
        return task.model(data["query"], data["reference"])


def keep_mask(queue_ids, query_ids):
    """B x size: a filled slot of another location."""
    return torch.tensor([[0 <= int(e) != int(q) for e in queue_ids] for q in query_ids])


def test_alpha_reaches_the_loss():
    task = tiny_task(alpha=1.0, queue_size=0)
    data = batch([0, 1, 2, 3], seed=0)
    query, reference = descriptors(task, data)
    loss = step(task, data, 0)["loss"]
    torch.testing.assert_close(loss, brute_force(query, reference, alpha=1.0))
    assert abs(loss - brute_force(query, reference, alpha=10.0)) > 1e-2  # alpha matters on this batch
    assert GMSTripletLoss(dim=8).alpha == 10.0  # CVM-Net / SAFA / the paper


def test_queue_is_filled_after_the_loss_and_masks_the_querys_location():
    task = tiny_task(queue_size=8)
    first = batch([0, 1, 2, 3], seed=1)
    query, reference = descriptors(task, first)
    out = step(task, first, 0)
    torch.testing.assert_close(out["loss"], brute_force(query, reference))  # the queue was still empty
    assert len(task.loss.queue) == 0  # training_step itself does not push
    task.on_train_batch_end(out)
    hardest = brute_hardest(query, reference, first["index"])
    queue = task.loss.queue
    assert queue.ids[:4].tolist() == first["index"][hardest].tolist() and queue.ids[4:].eq(-1).all()
    torch.testing.assert_close(task.loss.queue.descriptors[:4], reference[hardest])

    second = batch([2, 3, 4, 5], seed=2)  # locations 2 and 3 meet their own entries in the queue
    query, reference = descriptors(task, second)
    keep = keep_mask(task.loss.queue.ids, second["index"])
    assert keep[:, :4].any() and not keep[:, :4].all()  # the masking decides something on this batch
    expected = brute_force(query, reference, 10.0, task.loss.queue.descriptors.clone(), keep)
    loss = step(task, second, 0)["loss"]
    torch.testing.assert_close(loss, expected)
    assert abs(loss - brute_force(query, reference, 10.0, task.loss.queue.descriptors.clone())) > 1e-3


def test_queue_start_epoch_keeps_the_queue_out_until_then():
    """loss.queue_start_epoch: before it, no push and the loss ignores the queue (even a restored, filled one)."""
    task = tiny_task(queue_size=6, queue_start_epoch=2)
    data = batch([0, 1, 2], seed=3)
    query, reference = descriptors(task, data)
    g = torch.Generator().manual_seed(4)
    task.loss.queue.push(torch.nn.functional.normalize(torch.randn(4, 8, generator=g), dim=1),
                         torch.tensor([0, 7, 8, 9]))
    stored = task.loss.queue.ids.clone()
    in_batch = brute_force(query, reference)
    for epoch in (0, 1):
        out = step(task, data, epoch)
        task.on_train_batch_end(out)
        assert torch.equal(task.loss.queue.ids, stored)
        torch.testing.assert_close(out["loss"], in_batch)
    keep = keep_mask(task.loss.queue.ids, data["index"])
    with_queue = brute_force(query, reference, 10.0, task.loss.queue.descriptors.clone(), keep)
    assert abs(with_queue - in_batch) > 1e-3
    out = step(task, data, 2)
    torch.testing.assert_close(out["loss"], with_queue)
    task.on_train_batch_end(out)
    hard = data["index"][brute_hardest(query, reference, data["index"])].tolist()
    assert task.loss.queue.ids.tolist() == [hard[2], 7, 8, 9, hard[0], hard[1]]  # FIFO: the oldest entry (0) goes
