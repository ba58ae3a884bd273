"""Optimizing N candidate poses in parallel against one observed image (thesis section 3.3).

Each candidate is ``T = C exp([S] theta) C^-1 T0``: screw coordinates ``theta`` (angular part first)
act on the start pose ``T0`` about the point ``C`` (the target centre by default, so a rotation turns the
camera around the target instead of swinging the target out of view; ``screw_origin="world"`` gives the
thesis' plain ``exp([S] theta) T0`` about the model-frame origin). All candidates' rays go through the
model in chunked batches; each chunk's loss is back-propagated before the next is rendered, and the
accumulated pose gradient is pushed into ``theta`` once per iteration. Adam, exponentially decaying
learning rate.
"""

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3
from nerfinv_plugin.inversion.losses import LossName, per_ray_loss
from nerfinv_plugin.inversion.sampling import PixelSampler
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, render_chunks


@dataclass
class OptimizerConfig:
    """Gradient descent on the candidates of one Monte Carlo step."""

    iterations: int = 60
    """Iterations per Monte Carlo step (the thesis used 60)."""
    lr: float = 0.01
    """Adam learning rate at the start of each step (the thesis' 0.01)."""
    lr_decay: float = 0.8
    """Multiplies the learning rate every ``lr_decay_iterations`` iterations, smoothly (iNeRF's 0.8)."""
    lr_decay_iterations: int = 20
    loss: LossName = "mse"
    """Photometric loss: mse (thesis), mape (Parallel Inversion) or huber."""
    screw_origin: Literal["target", "world"] = "target"
    """Point the screw motions turn about: the target centre, or the model frame's origin (thesis)."""
    patience: int | None = None
    """Stop a step early when the best loss has not improved by min-improvement for this many iterations
    (beyond the thesis). Unset: always run every iteration."""
    min_improvement: float = 0.01
    """Relative improvement of the best loss that counts as progress for patience."""
    prune_every: int | None = None
    """Every this many iterations, stop optimizing (and rendering) candidates whose loss is more than
    prune-ratio times the best, never leaving fewer than the step keeps (successive halving, beyond the
    thesis). Unset: never."""
    prune_ratio: float = 2.0
    """How far above the best loss a candidate may be and stay in the step."""


@dataclass(frozen=True)
class IterationRecord:
    """One gradient iteration of a step, as the history keeps it."""

    loss: np.ndarray
    """[N] loss of every candidate on the iteration's pixels; ``inf`` for dropped and pruned candidates."""
    error_deg: np.ndarray | None = None
    """[N] rotation error of every candidate (degrees) at the poses the loss was measured at, when the
    truth is known."""


@dataclass
class StepResult:
    """Candidates after one step of optimization."""

    c2w: Tensor
    """[N, 4, 4] final poses (model frame, OpenGL axes)."""
    losses: Tensor
    """[N] loss of each final pose on the frame's evaluation pixels; ``inf`` for dropped candidates."""
    history: list[IterationRecord] = field(default_factory=list)
    """One record per iteration run."""
    dropped: list[int] = field(default_factory=list)
    """Candidates removed because their pose, loss or gradient became NaN or infinite."""
    pruned: list[int] = field(default_factory=list)
    """Candidates stopped early because their loss was far above the best (``prune_every``)."""


def _centred(centre: Tensor) -> tuple[Tensor, Tensor]:
    to_centre = torch.eye(4, dtype=centre.dtype, device=centre.device)
    to_centre[:3, 3] = centre
    from_centre = torch.eye(4, dtype=centre.dtype, device=centre.device)
    from_centre[:3, 3] = -centre
    return to_centre, from_centre


def candidate_losses(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor, observed: Tensor,
                     loss: LossName, backward: bool) -> Tensor:
    """Mean loss of each candidate [N] over ``pixels``; with ``backward``, gradients accumulate into
    ``c2w.grad`` chunk by chunk, so memory stays bounded by one chunk."""
    n, p = c2w.shape[0], pixels.shape[0]
    totals = torch.zeros(n, dtype=torch.float32, device=loaded.device)
    targets = observed.repeat(n, 1)
    candidate_of_ray = torch.arange(n, device=loaded.device).repeat_interleave(p)
    with torch.set_grad_enabled(backward):
        for part, out in render_chunks(loaded, c2w, intrinsics, pixels):
            per_ray = per_ray_loss(loss, out.rgb, targets[part]) / p
            if backward and per_ray.requires_grad:  # rays that missed the target carry no gradient
                # Non-finite rays must not poison the others' gradients; their candidates get dropped.
                torch.where(torch.isfinite(per_ray), per_ray, 0.0).sum().backward()
            totals.index_add_(0, candidate_of_ray[part], per_ray.detach())
    return totals


def optimize_candidates(loaded: LoadedModel, start: Tensor, observed: Tensor, intrinsics: Intrinsics,
                        sampler: PixelSampler, eval_pixels: Tensor, centre: Tensor, config: OptimizerConfig,
                        rng: np.random.Generator,
                        error_fn: Callable[[Tensor], Tensor] | None = None,
                        on_iteration: Callable[[int, IterationRecord], None] | None = None,
                        min_candidates: int = 1) -> StepResult:
    """Optimize candidates ``start`` [N, 4, 4] against ``observed`` [H, W, 3] (float in [0, 1]).

    ``sampler`` must be prepared on the observed image; it draws fresh pixels each iteration, shared by all
    candidates. Final losses are measured on ``eval_pixels`` [E, 2], fixed for the frame, so candidates
    (and steps) are ranked on the same pixels. ``error_fn`` maps poses [N, 4, 4] to errors in degrees,
    recorded in the history when the truth is known. ``on_iteration(i, record)`` sees each iteration's
    history record as it is made (progress bars). Pruning never leaves fewer than ``min_candidates``.
    """
    device = loaded.device
    start = start.to(device, torch.float32)
    n = start.shape[0]
    theta = torch.zeros(n, 6, device=device, requires_grad=True)
    to_c, from_c = _centred(centre.to(device, torch.float32)) if config.screw_origin == "target" else \
        (torch.eye(4, device=device), torch.eye(4, device=device))
    optimizer = torch.optim.Adam([theta], lr=config.lr)
    gamma = config.lr_decay ** (1.0 / config.lr_decay_iterations)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=gamma)
    alive = torch.ones(n, dtype=torch.bool, device=device)
    """Not dropped for a non-finite pose, loss or gradient."""
    active = alive.clone()
    """Alive and not pruned: still rendered and optimized."""
    history = []
    best_seen, stalled = float("inf"), 0

    def poses() -> Tensor:
        return to_c @ exp_se3(theta) @ from_c @ start

    for iteration in range(config.iterations):
        pixels = torch.as_tensor(sampler.sample(rng), device=device)
        c2w = poses()
        rendered = torch.nonzero(active).flatten()
        leaf = c2w[rendered].detach().requires_grad_(True)
        losses = torch.full((n,), torch.inf, device=device)
        losses[rendered] = candidate_losses(loaded, leaf, intrinsics, pixels, observed[pixels[:, 0], pixels[:, 1]],
                                            config.loss, backward=True)
        grad = torch.zeros_like(c2w)
        grad[rendered] = leaf.grad
        # A pose, loss or gradient that is not finite ends the candidate. nerfstudio's renderer turns NaN
        # colours into 0 in eval mode, so a NaN pose alone would still get a finite loss.
        finite = torch.isfinite(losses) & torch.isfinite(c2w).flatten(1).all(1) & torch.isfinite(grad).flatten(1).all(1)
        alive &= ~active | finite
        active &= alive
        optimizer.zero_grad(set_to_none=True)
        c2w.backward(torch.where(active[:, None, None], grad, 0.0))
        optimizer.step()
        scheduler.step()
        losses = torch.where(active, losses, torch.inf)
        record = IterationRecord(losses.cpu().numpy(),
                                 None if error_fn is None else error_fn(c2w.detach()).cpu().numpy())
        history.append(record)
        if on_iteration is not None:
            on_iteration(iteration, record)
        if not bool(active.any()):
            break
        if config.prune_every and (iteration + 1) % config.prune_every == 0:
            active &= ~_far_above_best(losses, config.prune_ratio, min_candidates)
        best = float(losses.min())
        stalled = 0 if best < best_seen * (1.0 - config.min_improvement) else stalled + 1
        best_seen = min(best_seen, best)
        if config.patience is not None and stalled >= config.patience:
            break
    final = poses().detach()
    losses = torch.full((n,), torch.inf, device=device)
    kept = torch.nonzero(active).flatten()
    losses[kept] = candidate_losses(loaded, final[kept], intrinsics, eval_pixels.to(device),
                                    observed[eval_pixels[:, 0], eval_pixels[:, 1]], config.loss, backward=False)
    alive &= ~active | torch.isfinite(losses)
    losses = torch.where(active & alive, losses, torch.inf)
    dropped = torch.nonzero(~alive).flatten().tolist()
    pruned = torch.nonzero(alive & ~active).flatten().tolist()
    return StepResult(final, losses, history, dropped, pruned)


def _far_above_best(losses: Tensor, ratio: float, keep: int) -> Tensor:
    """Candidates [N] (bool) whose loss is more than ``ratio`` times the best, sparing the ``keep`` best."""
    far = losses > ratio * losses.min()
    far[torch.argsort(losses)[:keep]] = False
    return far & torch.isfinite(losses)
