"""InfoNCE's settings reach the formula: the default temperatures (0.1 for the function, CLIP's 0.07 for the
module: docs/conventions.md "Symmetric InfoNCE"), the bounds on temperature and label smoothing, and the module
passing labels and smoothing on to info_nce."""
import math

import pytest
import torch
import torch.nn.functional as F
from geoloc.losses import info_nce
from geoloc.losses.infonce import InfoNCELoss


def pairs(seed=0):
    g = torch.Generator().manual_seed(seed)
    query = F.normalize(torch.randn(6, 5, generator=g, dtype=torch.float64), dim=1)
    reference = F.normalize(query + 0.5 * torch.randn(6, 5, generator=g, dtype=torch.float64), dim=1)
    return query, reference


def test_default_temperatures():
    query, reference = pairs()
    torch.testing.assert_close(info_nce(query, reference), info_nce(query, reference, 0.1))
    assert float(InfoNCELoss().temperature) == pytest.approx(0.07, rel=1e-6)
    assert InfoNCELoss(learn_temperature=True).log_inv_temperature.item() == pytest.approx(math.log(1 / 0.07))


def test_module_passes_labels_and_smoothing_on():
    query, reference = pairs(1)
    labels = torch.tensor([0, 0, 1, 2, 2, 3])  # places 0 and 2 seen twice
    loss = InfoNCELoss(temperature=0.1, label_smoothing=0.1)
    expected = info_nce(query, reference, 0.1, labels, 0.1)
    torch.testing.assert_close(loss(query, reference, labels).double(), expected.double())
    assert abs(float(expected) - float(info_nce(query, reference, 0.1, None, 0.1))) > 1e-3  # labels matter
    assert abs(float(expected) - float(info_nce(query, reference, 0.1, labels))) > 1e-3  # smoothing matters


def test_bounds_are_refused_with_the_value():
    query, reference = pairs()
    with pytest.raises(ValueError, match=r"label_smoothing must be in \[0, 1\), got 1.0"):
        info_nce(query, reference, label_smoothing=1.0)
    with pytest.raises(ValueError, match="loss.temperature must be > 0, got 0"):
        InfoNCELoss(temperature=0)
