"""How a speed benchmark renders our side: ``ns-invert``'s ``--render`` options, resolved into the
:class:`~nerfinv_plugin.model.render.RenderSettings` value each render call is given.

The speed benchmarks render the same model two ways (as trained, and with our inversion-time sampling)
in one process; the model itself is never changed, so nothing has to be put back.
"""

from dataclasses import dataclass

import torch

from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import RenderSettings, render_settings


@dataclass(frozen=True)
class Sampling:
    """How our side of a speed benchmark renders (``ns-invert``'s ``--render`` options)."""

    target_radius_m: float | None = 1.0
    """Rays sampled only within this radius (dataset metres) of the target centre. Unset: the model's
    near and far planes."""
    proposal_samples: tuple[int, ...] | None = (8, 4)
    """Samples per ray of each proposal level. Unset: as the model has them."""
    nerf_samples: int | None = 8
    """Samples per ray of the final field. Unset: as the model has them."""

    def sphere(self, loaded: LoadedModel, centre: torch.Tensor) -> tuple[torch.Tensor, float] | None:
        """The target sphere in the model frame about ``centre`` [3] (model frame), or ``None``."""
        if self.target_radius_m is None:
            return None
        return centre.to(loaded.device, torch.float32), self.target_radius_m * loaded.dataparser_scale

    def settings(self, loaded: LoadedModel, centre: torch.Tensor) -> RenderSettings:
        """The render settings these values give about ``centre`` [3] (model frame), checked against the
        model (the chunk size measured again when the sample counts change)."""
        return render_settings(loaded, self.sphere(loaded, centre), self.proposal_samples, self.nerf_samples)


AS_TRAINED = Sampling(None, None, None)
"""The model's own near/far and sample counts: how the thesis' implementation renders."""
