"""An optimizer plug-in: SGD with momentum and a constant learning rate."""

import torch
from geoloc.registry import register


@register("optimizer", "sgd")
def sgd(params, lr: float = 0.01, momentum: float = 0.9):
    return torch.optim.SGD(params, lr=lr, momentum=momentum), None
