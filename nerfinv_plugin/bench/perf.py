"""Inversion throughput, measured the same way for the thesis' implementation and for ours.

The thesis' loop (its section 4.3): every iteration detects keypoints in the observed image, draws the
pixels, renders each candidate through the patched ``get_outputs_for_camera_ray_bundle`` with the
model's weights trainable, stacks the losses, back-propagates once and steps Adam on screw parameters
about the world origin. Ours is :func:`optimize_candidates` with the settings ``ns-invert`` runs with.
Both see the same model, frame, starting poses and number of pixels.
"""

import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import psutil
import torch
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3
from nerfinv_plugin.inversion.optimizer import OptimizerConfig, optimize_candidates
from nerfinv_plugin.inversion.sampling import PixelSampler
from nerfinv_plugin.model.fused_hash import stock_hash_encoding
from nerfinv_plugin.model.gradients import keep_gradients
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, pinhole_cameras


@dataclass(frozen=True)
class Timing:
    seconds: float
    iterations: int
    rays_per_iteration: int
    peak_memory_bytes: int
    """Largest growth of the process' resident memory (CPU) or of allocated CUDA memory during the run."""

    @property
    def per_iteration(self) -> float:
        return self.seconds / self.iterations

    @property
    def rays_per_second(self) -> float:
        return self.rays_per_iteration * self.iterations / self.seconds


@contextmanager
def peak_memory(device: torch.device):
    """Yields a callable returning the peak memory growth since entry: CUDA's allocator statistics, or the
    resident set size sampled every 5 ms on the CPU (the process' own memory, whatever allocated it)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        yield lambda: torch.cuda.max_memory_allocated(device) - base
        return
    process = psutil.Process()
    base = process.memory_info().rss
    peak, stop = [base], threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], process.memory_info().rss)
            time.sleep(0.005)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        yield lambda: peak[0] - base
    finally:
        stop.set()
        thread.join()


def _timed(device: torch.device, rays: int, iterations: int, work: Callable[[], None]) -> Timing:
    with peak_memory(device) as peak:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        tic = time.perf_counter()
        work()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds = time.perf_counter() - tic
    return Timing(seconds, iterations, rays, int(peak()))


def thesis_step(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor, target: Tensor) -> Tensor:
    """One iteration as the thesis' implementation does it: a ray bundle per candidate, rendered through
    the patched ``get_outputs_for_camera_ray_bundle`` of stock nerfstudio (its own hash-grid forward)
    with the model's weights not frozen, the candidates' losses stacked and back-propagated once.
    ``c2w`` is [N, 3, 4]. Returns the rendered colours [N, P, 3]."""
    model = loaded.model
    rgbs, losses = [], []
    with keep_gradients(model), stock_hash_encoding(model):
        for n in range(c2w.shape[0]):
            camera = pinhole_cameras(c2w[n:n + 1], intrinsics).to(loaded.device)
            bundle = camera.generate_rays(camera_indices=0, coords=pixels.float() + 0.5)
            rgb = model.get_outputs_for_camera_ray_bundle(bundle.reshape((pixels.shape[0], 1)))["rgb"][:, 0]
            rgbs.append(rgb)
            losses.append(((rgb - target) ** 2).mean())
    torch.stack(losses).sum().backward()
    return torch.stack(rgbs)


def thesis_loop(loaded: LoadedModel, start: Tensor, image: np.ndarray, intrinsics: Intrinsics, pixels: int,
                iterations: int, lr: float = 0.01, seed: int = 0) -> Timing:
    """The thesis' implementation, iteration by iteration (see the module docstring)."""
    device = loaded.device
    observed = torch.as_tensor(image, dtype=torch.float32, device=device) / 255.0
    theta = torch.zeros(start.shape[0], 6, device=device, requires_grad=True)
    optimizer = torch.optim.Adam([theta], lr=lr)
    rng = np.random.default_rng(seed)
    start = start.to(device, torch.float32)

    def work() -> None:
        loaded.model.requires_grad_(True)
        try:
            for _ in range(iterations):
                chosen = torch.as_tensor(PixelSampler("interest_region", pixels).prepare(image).sample(rng),
                                         device=device)
                optimizer.zero_grad(set_to_none=True)
                c2w = (exp_se3(theta) @ start)[:, :3]
                thesis_step(loaded, c2w, intrinsics, chosen, observed[chosen[:, 0], chosen[:, 1]])
                optimizer.step()
        finally:
            loaded.model.requires_grad_(False)
            loaded.model.zero_grad(set_to_none=True)

    return _timed(device, start.shape[0] * pixels, iterations, work)


def our_loop(loaded: LoadedModel, start: Tensor, image: np.ndarray, intrinsics: Intrinsics, pixels: int,
             centre: Tensor, config: OptimizerConfig, seed: int = 0) -> Timing:
    """One Monte Carlo step of our engine: keypoints once, all candidates batched, frozen weights."""
    observed = torch.as_tensor(image, dtype=torch.float32, device=loaded.device) / 255.0
    rng = np.random.default_rng(seed)
    sampler = PixelSampler("interest_region", pixels).prepare(image)
    eval_pixels = torch.as_tensor(PixelSampler("random", 1024).prepare(image).sample(rng))
    history: list = []

    def work() -> None:
        history.extend(optimize_candidates(loaded, start, observed, intrinsics, sampler, eval_pixels, centre, config,
                                           rng).history)

    timing = _timed(loaded.device, start.shape[0] * pixels, config.iterations, work)
    return Timing(timing.seconds, len(history), timing.rays_per_iteration, timing.peak_memory_bytes)
