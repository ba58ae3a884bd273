"""Photometric losses, per ray, so that chunks can be back-propagated one at a time."""

from typing import Literal

import torch
from torch import Tensor

LossName = Literal["mse", "mape", "huber"]

HUBER_DELTA = 0.1
MAPE_EPS = 0.01


def per_ray_loss(name: LossName, predicted: Tensor, observed: Tensor) -> Tensor:
    """Loss of each ray [R] from colours [R, 3]. ``mape`` (Parallel Inversion): absolute error relative
    to the observed colour (plus 0.01, so black pixels do not divide by zero); ``huber``: quadratic below
    0.1, linear above, robust to specular highlights the model did not learn."""
    diff = predicted - observed
    if name == "mse":
        return (diff**2).mean(-1)
    if name == "mape":
        return (diff.abs() / (observed.abs() + MAPE_EPS)).mean(-1)
    if name == "huber":
        return torch.nn.functional.huber_loss(predicted, observed, reduction="none", delta=HUBER_DELTA).mean(-1)
    raise ValueError(f"unknown loss {name!r}; choose mse, mape or huber")


def per_candidate_loss(name: LossName, predicted: Tensor, observed: Tensor) -> Tensor:
    """One loss per candidate [N] from colours [N, P, 3] against observed [P, 3]."""
    return per_ray_loss(name, predicted, observed.expand_as(predicted)).mean(-1)
