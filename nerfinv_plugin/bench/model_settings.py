"""The one place where a benchmark changes how a loaded model renders, and changes it back.

The speed benchmarks render the same model two ways (as trained, and with our inversion-time sampling)
in one process, and the bank benchmark bounds rays the way ``ns-invert`` does. Today those settings live
on the model itself (the target sphere on :class:`LoadedModel`, sample counts on nerfacto's proposal
sampler, and the chunk size that follows them), so every change is made here, inside a block that
restores what it found, also after an exception: a benchmark never leaves the model it was given
rendering differently.
"""

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import set_sample_counts


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


AS_TRAINED = Sampling(None, None, None)
"""The model's own near/far and sample counts: how the thesis' implementation renders."""


@contextmanager
def model_settings(loaded: LoadedModel, sphere: tuple[torch.Tensor, float] | None = None,
                   proposal: tuple[int, ...] | None = None, nerf: int | None = None) -> Iterator[LoadedModel]:
    """Within the block, ``loaded`` bounds rays to ``sphere`` (``None``: not bounded) and takes ``proposal``
    / ``nerf`` samples per ray (``None``: as it has them); code inside may change these settings further
    (``bound_rays`` does). On exit the target sphere, the sample counts and the chunk size are put back
    exactly as they were, without re-measuring anything."""
    sampler = getattr(loaded.model, "proposal_sampler", None)
    saved_counts = None if sampler is None else (sampler.num_proposal_samples_per_ray,
                                                 sampler.num_nerf_samples_per_ray)
    saved_sphere, saved_chunk = loaded.target_sphere, loaded.chunk_rays
    try:
        loaded.target_sphere = sphere
        if proposal is not None or nerf is not None:
            set_sample_counts(loaded, proposal, nerf)
        yield loaded
    finally:
        loaded.target_sphere, loaded.chunk_rays = saved_sphere, saved_chunk
        if saved_counts is not None:
            sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray = saved_counts


@contextmanager
def sampled(loaded: LoadedModel, sampling: Sampling, centre: torch.Tensor) -> Iterator[LoadedModel]:
    """:func:`model_settings` with ``sampling``'s values about ``centre`` [3] (model frame)."""
    with model_settings(loaded, sampling.sphere(loaded, centre), sampling.proposal_samples,
                        sampling.nerf_samples) as model:
        yield model
