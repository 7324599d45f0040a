"""A loss gets what it names of the batch beyond (query, reference, labels); the built-in losses are called
exactly as before, with the descriptors alone."""
from types import SimpleNamespace

import torch
from geoloc.losses.triplet import soft_margin_triplet

import conftest
from conftest import REPO


def _batch(n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"query": torch.randn(n, 3, 32, 32, generator=g), "reference": torch.randn(n, 3, 32, 32, generator=g),
            "index": torch.arange(n), "label": torch.arange(n)}


def test_a_loss_that_names_the_batch_and_the_maps_gets_them():
    torch.manual_seed(0)
    plugin = str(REPO / "tests/plugins/tile_position_loss.py")
    task = conftest.tiny_task(loss={"name": "tile_position", "module": plugin})
    assert task.loss_extras == ("batch", "reference_features")
    data = _batch()
    loss = task.training_step(data, SimpleNamespace(epoch=0))["loss"]
    (batch, features), = task.loss.seen
    assert batch is data
    with torch.no_grad():  # train-mode batch statistics depend on the batch only: a second pass agrees
        query, reference = task.model(data["query"], data["reference"])
        torch.testing.assert_close(features.descriptor, reference)
    assert len(features.maps) == 3 and features.head_map.shape[:2] == (4, 4) and features.attention is not None
    torch.testing.assert_close(loss, soft_margin_triplet(query, reference))
    loss.backward()
    assert task.model.reference.head.descriptor.proj.weight.grad is not None


def test_the_built_in_losses_see_only_the_descriptors(monkeypatch):
    """gms_triplet and infonce are called as loss(query, reference, labels): no keyword, no feature pass."""
    for loss in ({"name": "gms_triplet", "queue_size": 0}, {"name": "infonce"}):
        torch.manual_seed(0)
        task = conftest.tiny_task(loss=loss)
        assert task.loss_extras == ()
        calls, real = [], type(task.loss).forward

        def spy(self, *args, **kwargs):
            calls.append((len(args), kwargs))
            return real(self, *args, **kwargs)

        monkeypatch.setattr(type(task.loss), "forward", spy)
        monkeypatch.setattr(task.model, "features", lambda *a: (_ for _ in ()).throw(AssertionError("maps")))
        task.training_step(_batch(), SimpleNamespace(epoch=0))
        assert calls == [(3, {})]
        monkeypatch.undo()
