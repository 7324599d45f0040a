"""A loss gets what it declares in `needs` beyond (query, reference, labels); the built-in losses are called
exactly as before, with the descriptors alone."""
from types import SimpleNamespace

import pytest
import torch
from geoloc.config import ConfigError
from geoloc.losses.triplet import soft_margin_triplet
from geoloc.tasks.crossview.task import loss_needs

import conftest
from conftest import REPO


def _batch(n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"query": torch.randn(n, 3, 32, 32, generator=g), "reference": torch.randn(n, 3, 32, 32, generator=g),
            "index": torch.arange(n), "label": torch.arange(n)}


def test_a_loss_that_declares_the_batch_and_the_maps_gets_them():
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


def test_a_loss_from_before_needs_is_read_off_its_signature_with_a_warning():
    class Old(torch.nn.Module):
        def forward(self, query, reference, labels, batch):
            return query.sum()

    with pytest.warns(DeprecationWarning, match=r"declare them instead: `needs = \('batch',\)`"):
        assert loss_needs(Old()) == ("batch",)


def test_a_declared_need_the_task_does_not_give_is_refused():
    class Wrong(torch.nn.Module):
        needs = ("batch", "depth_map")

    with pytest.raises(ConfigError, match=r"declares needs=\('batch', 'depth_map'\).*'query_features'"):
        loss_needs(Wrong())
    Wrong.needs = "batch"  # a string, not a tuple of names
    with pytest.raises(ConfigError, match="a tuple of names"):
        loss_needs(Wrong())


def test_what_a_loss_declares_is_what_it_gets_not_what_its_signature_names():
    class Declared(torch.nn.Module):
        needs = ()

        def forward(self, query, reference, labels, batch=None):
            return query.sum()

    assert loss_needs(Declared()) == ()
