"""A per-frame gain and bias between the observed image and the model, for images from another camera and light.

A model trained on clean renders sees a lab frame (another sun colour, exposure, a lifted and noisy
background) as if every pixel were wrong, and a photometric loss then prefers poses that put dark or bright
parts where the exposure moved them. Per colour channel, ``observed ~ gain * rendered + bias`` holds to a
first order for all of these (the display gamma only bends it). Once per frame, before its first step, the
model is rendered at the best candidate the frame starts from, on the frame's ranking pixels, the six
numbers are fitted by least squares, and the observed colours are mapped back to the model's scale,
``(observed - bias) / gain``, for every iteration and the ranking of that frame. A frame keeps one mapping,
so that its steps and candidates are compared on one scale.

``candidate-gain-bias`` fits the six numbers for every candidate instead, on its own render: a wrong pose
cannot borrow the mapping of the frame's best start, and a colour that the model renders otherwise than the
frame shows it (a view-dependent tint the model did not learn) is not read as a pose error. During a step a
candidate's mapping comes from its previous iteration's render (no second render; the first iteration
compares as observed); the ranking fits it on the ranking pixels themselves.
"""

from dataclasses import dataclass

import torch
from torch import Tensor

MIN_GAIN, MAX_GAIN = 0.25, 4.0
"""A fitted gain outside this range means the fit saw no object (a wrong start, an empty frame), not a
camera: the gain is clamped to it."""
MIN_SPREAD = 1e-3
"""A channel whose rendered colours vary less than this (standard deviation, on [0, 1]) cannot fix a gain:
it keeps gain 1 and only its bias is fitted."""


@dataclass(frozen=True)
class GainBias:
    """Per-channel ``observed = gain * model + bias``."""

    gain: Tensor
    """[3]"""
    bias: Tensor
    """[3]"""

    @classmethod
    def identity(cls) -> "GainBias":
        return cls(torch.ones(3), torch.zeros(3))

    @classmethod
    def fit(cls, rendered: Tensor, observed: Tensor) -> "GainBias":
        """Least squares per channel from colours [P, 3] rendered by the model and observed at the same pixels."""
        gain, bias = fit_each(rendered.cpu()[None], observed.cpu())
        return cls(gain[0], bias[0])

    def to_model(self, observed: Tensor) -> Tensor:
        """Observed colours [..., 3] in [0, 1] mapped to the model's scale."""
        return (observed - self.bias.to(observed.device)) / self.gain.to(observed.device)

    def to_dict(self) -> dict:
        return {"gain": self.gain.tolist(), "bias": self.bias.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> "GainBias":
        return cls(torch.tensor(data["gain"], dtype=torch.float32), torch.tensor(data["bias"], dtype=torch.float32))


def fit_each(rendered: Tensor, observed: Tensor) -> tuple[Tensor, Tensor]:
    """Per candidate and channel, the least-squares ``observed = gain * rendered + bias`` from the colours
    [N, P, 3] each candidate renders at pixels whose observed colours are [P, 3]: gain and bias [N, 3]
    (float32, on ``rendered``'s device)."""
    rendered, observed = rendered.detach().double(), observed.detach().double().to(rendered.device)
    mean_r, mean_o = rendered.mean(1, keepdim=True), observed.mean(0)
    covariance = ((rendered - mean_r) * (observed - mean_o)).mean(1)
    variance = ((rendered - mean_r) ** 2).mean(1)
    fitted = covariance / variance.clamp_min(1e-12)
    gain = torch.where(variance.sqrt() > MIN_SPREAD, fitted, torch.ones_like(fitted)).clamp(MIN_GAIN, MAX_GAIN)
    bias = mean_o - gain * mean_r[:, 0]
    return gain.float(), bias.float()
