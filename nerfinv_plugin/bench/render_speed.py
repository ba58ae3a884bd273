"""Forward+backward throughput of one inversion iteration, our batched renderer against the thesis'.

Both ways render the same candidates at the same pixels, alternately in one process (so a machine that
slows down mid-run slows both): the thesis' way is :func:`perf.thesis_step` (a ray bundle per candidate
through the patched ``get_outputs_for_camera_ray_bundle``, stock hash forward, weights trainable, the
model's own sampling); ours is ``optimizer.candidate_losses`` (all candidates' rays in chunks, fused
hash forward, frozen weights, :class:`Sampling`'s bounded rays and sample counts).
"""

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.bench.perf import thesis_step
from nerfinv_plugin.bench.sampling import Sampling
from nerfinv_plugin.inversion.optimizer import candidate_losses
from nerfinv_plugin.inversion.starts import sphere_shell
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import AS_TRAINED, Intrinsics, RenderSettings, bound_to_target, ray_bundle, render
from nerfinv_plugin.synth.datasets import speedplus_like_camera


@dataclass(frozen=True)
class RenderSpeed:
    """Timed iterations of both ways, and how far apart their colours are."""

    rays: int
    """Candidates x pixels rendered per iteration."""
    chunk_rays: int
    """Rays per chunk on our side."""
    thesis_s: list[float]
    ours_s: list[float]
    colour_diff_mean: float
    """Mean absolute difference between the two ways' colours of the same rays."""
    colour_diff_max: float

    @property
    def thesis_median_s(self) -> float:
        return statistics.median(self.thesis_s)

    @property
    def ours_median_s(self) -> float:
        return statistics.median(self.ours_s)

    @property
    def ratio(self) -> float:
        """Thesis time over ours (median iterations): how many times faster ours is."""
        return self.thesis_median_s / self.ours_median_s


@dataclass(frozen=True)
class RenderProblem:
    """Candidates and pixels that both ways render."""

    c2w: Tensor
    """[N, 3, 4] model frame, on the model's device."""
    intrinsics: Intrinsics
    pixels: Tensor
    """[P, 2] (row, col), shared by all candidates."""
    centre: Tensor
    """[3] the dataset origin in the model frame: the target the cameras look at."""


def render_problem(loaded: LoadedModel, candidates: int, pixels: int, range_m: float, width: int, height: int,
                   sampling: Sampling, on_target: bool, seed: int = 0) -> RenderProblem:
    """``candidates`` random cameras ``range_m`` (dataset units) from the dataset origin looking at it, with
    SPEED+'s field of view at ``width`` x ``height``, and ``pixels`` distinct pixels: anywhere in the image,
    or with ``on_target`` only where the first camera's rays cross ``sampling``'s target sphere (as
    interest-region pixels on the object are; rays that miss it cost ours nothing)."""
    rng = np.random.default_rng(seed)
    camera = speedplus_like_camera(width, height)
    intrinsics = Intrinsics.from_opencv(camera.matrix, width, height)
    poses = loaded.dataset_to_model(sphere_shell(candidates, range_m, np.zeros(3), rng))
    c2w = torch.as_tensor(poses[:, :3], dtype=torch.float32, device=loaded.device)
    centre = torch.as_tensor(loaded.point_to_model(np.zeros(3)), dtype=torch.float32)
    allowed = np.arange(width * height)
    if on_target and sampling.target_radius_m is not None:
        everywhere = torch.as_tensor(np.stack([allowed // width, allowed % width], 1))
        bounded = RenderSettings(Sampling(sampling.target_radius_m, None, None).sphere(loaded, centre))
        hits = bound_to_target(bounded, ray_bundle(loaded, c2w[:1], intrinsics, everywhere))
        allowed = allowed[hits.cpu().numpy()]
    flat = rng.choice(allowed, size=pixels, replace=False)
    chosen = torch.as_tensor(np.stack([flat // width, flat % width], 1), device=loaded.device)
    return RenderProblem(c2w, intrinsics, chosen, centre)


def _sync(loaded: LoadedModel) -> None:
    if loaded.device.type == "cuda":
        torch.cuda.synchronize(loaded.device)


def _batched_step(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor, target: Tensor,
                  settings: RenderSettings = AS_TRAINED) -> Tensor:
    """One iteration of our engine under ``settings``: each chunk's loss back-propagated before the next
    chunk is rendered."""
    return candidate_losses(loaded, c2w, intrinsics, pixels, target, "mse", backward=True, settings=settings)


def render_speed(loaded: LoadedModel, problem: RenderProblem, sampling: Sampling, repeats: int) -> RenderSpeed:
    """Time one warm-up then ``repeats`` iterations of each way, alternately; the loss is MSE against black."""
    target = torch.zeros(problem.pixels.shape[0], 3, device=loaded.device)
    settings = sampling.settings(loaded, problem.centre)

    def timed(step: Callable[..., Tensor], ours: bool) -> tuple[float, Tensor]:
        """(seconds, what the step returns), with the weights frozen for ours and trainable for the thesis."""
        leaf = problem.c2w.clone().requires_grad_(True)
        loaded.model.requires_grad_(not ours)
        try:
            _sync(loaded)
            start = time.perf_counter()
            result = (step(loaded, leaf, problem.intrinsics, problem.pixels, target, settings) if ours else
                      step(loaded, leaf, problem.intrinsics, problem.pixels, target))
            _sync(loaded)
            return time.perf_counter() - start, result
        finally:
            loaded.model.requires_grad_(False)
            loaded.model.zero_grad(set_to_none=True)

    _, rgb_thesis = timed(thesis_step, ours=False)
    timed(_batched_step, ours=True)
    with torch.no_grad():
        rgb_ours = render(loaded, problem.c2w, problem.intrinsics, problem.pixels, settings).rgb
    chunk_rays = settings.chunk_rays or loaded.chunk_rays
    thesis_s, ours_s = [], []
    for _ in range(repeats):
        thesis_s.append(timed(thesis_step, ours=False)[0])
        ours_s.append(timed(_batched_step, ours=True)[0])
    diff = (rgb_thesis.detach() - rgb_ours).abs()
    return RenderSpeed(int(problem.c2w.shape[0] * problem.pixels.shape[0]), chunk_rays, thesis_s, ours_s,
                       float(diff.mean()), float(diff.max()))
