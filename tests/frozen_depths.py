"""Renders whose sample depths stay where the first render put them, for finite differences that measure
exactly the function autograd differentiates."""

import contextlib


@contextlib.contextmanager
def frozen_sample_depths(model):
    """nerfacto places samples with proposal networks whose output is detached: the pose gradient treats
    the sample depths along each ray as constants. Within this block the depths found on the first
    render are reused for later renders (new poses move the samples with the rays, as the gradient
    assumes), so finite differences measure exactly the function that autograd differentiates."""
    sampler = model.proposal_sampler
    original = sampler.forward
    cache = {}

    def replay(ray_bundle, density_fns=None):
        if "samples" not in cache:
            cache["samples"] = original(ray_bundle, density_fns=density_fns)
            return cache["samples"]
        samples, weights_list, samples_list = cache["samples"]
        fresh = ray_bundle.get_ray_samples(samples.frustums.starts, samples.frustums.ends, samples.spacing_starts,
                                           samples.spacing_ends, samples.spacing_to_euclidean_fn)
        return fresh, weights_list, samples_list

    sampler.forward = replay
    try:
        yield
    finally:
        del sampler.forward
