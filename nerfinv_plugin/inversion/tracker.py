"""The Monte Carlo schedule along a trajectory (thesis section 3.4).

Each Monte Carlo step optimizes the current candidates against one image, ranks them, and keeps the
best few; each kept pose spawns perturbed copies, and kept plus spawned poses start the next step. In
``trajectory`` mode the next step already looks at the next frame (the thesis' contribution: the search
narrows while the target moves); in ``fixed`` mode every step looks at the same image (parallel iNeRF).
The best candidate of a step is the estimate for its frame.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3, log_se3, perturb_about
from nerfinv_plugin.inversion.optimizer import OptimizerConfig, StepResult, optimize_candidates
from nerfinv_plugin.inversion.sampling import PixelSampler, Strategy
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics


@dataclass
class MonteCarloConfig:
    """How candidates are kept and spawned between steps."""

    mode: Literal["trajectory", "fixed"] = "trajectory"
    """trajectory: each step takes the next frame; fixed: every step uses the first frame."""
    keep: tuple[int, ...] = (3, 1)
    """Candidates kept after each step; the last entry repeats (the thesis' Lego runs: 3, then 1)."""
    keep_fraction: float | None = None
    """Instead of ``keep``: keep this fraction after the first step, halving it every step, at least one
    (Parallel Inversion: 0.25)."""
    spawn: int = 2
    """Perturbed copies spawned around each kept pose."""
    spawn_rot_deg: float = 5.0
    """Each Euler angle of a spawned copy is drawn from [-spawn_rot_deg, spawn_rot_deg] (about the target)."""
    spawn_trans_m: float = 0.05
    """Each axis of a spawned copy's shift is drawn from [-spawn_trans_m, spawn_trans_m] (dataset metres)."""
    reset_lr: bool = True
    """Start every step at the initial learning rate (thesis fig. 5.2); otherwise continue the decay."""
    motion_prior: bool = False
    """Trajectory mode: move the kept poses by the last frame-to-frame motion of the estimate (constant
    velocity) before spawning, instead of spawning around where the target was."""


def keep_count(config: MonteCarloConfig, step: int, candidates: int) -> int:
    """How many candidates survive step ``step`` (0-based) out of ``candidates``."""
    if config.keep_fraction is not None:
        wanted = int(round(candidates * config.keep_fraction / 2**step))
    else:
        wanted = config.keep[min(step, len(config.keep) - 1)]
    return max(1, min(wanted, candidates))


@dataclass
class Frame:
    """One observed image of the sequence, with its intrinsics (nerfstudio convention)."""

    image: np.ndarray
    """[H, W, 3] ``uint8`` RGB."""
    intrinsics: Intrinsics
    name: str = ""
    c2w_true: Tensor | None = None
    """[4, 4] true camera pose in the model frame, when known: for error histories."""


@dataclass
class StepRecord:
    """What one Monte Carlo step produced."""

    frame_index: int
    estimate: Tensor
    """[4, 4] best pose of the step (model frame)."""
    loss: float
    candidates: int
    result: StepResult
    kept: int = 0


@dataclass
class Tracker:
    """Runs the Monte Carlo schedule of a :class:`MonteCarloConfig` with the optimizer settings given."""

    loaded: LoadedModel
    centre: Tensor
    """Target centre in the model frame: perturbations and screw motions turn about it."""
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    monte_carlo: MonteCarloConfig = field(default_factory=MonteCarloConfig)
    sampling: Strategy = "interest_region"
    pixels: int = 256
    eval_pixels: int = 1024
    seed: int = 0
    error_fn: Callable[[Tensor, Tensor], Tensor] | None = None
    """``(poses [N, 4, 4], true pose [4, 4]) -> degrees [N]``, for histories when the truth is known."""

    def run(self, frames: Sequence[Frame], start: Tensor, steps: int | None = None,
            on_step: Callable[[StepRecord], None] | None = None) -> list[StepRecord]:
        """Track ``frames`` from the candidates ``start`` [N, 4, 4]. Trajectory mode runs one step per
        frame (``steps`` limits it); fixed mode runs ``steps`` steps on ``frames[0]``. ``on_step`` sees each
        record as soon as it exists (to write results as they come)."""
        mc = self.monte_carlo
        total = len(frames) if mc.mode == "trajectory" else (steps or 1)
        if mc.mode == "trajectory" and steps is not None:
            total = min(total, steps)
        rng = np.random.default_rng(self.seed)
        generator = torch.Generator().manual_seed(self.seed)
        scale = self.loaded.dataparser_scale
        candidates = start.to(torch.float32)
        records: list[StepRecord] = []
        for step in range(total):
            frame = frames[step if mc.mode == "trajectory" else 0]
            sampler = PixelSampler(self.sampling, self.pixels).prepare(frame.image)
            eval_pixels = torch.as_tensor(PixelSampler("random", self.eval_pixels).prepare(frame.image).sample(rng))
            observed = torch.as_tensor(frame.image, dtype=torch.float32, device=self.loaded.device) / 255.0
            optimizer = self.optimizer if mc.reset_lr or step == 0 else _decayed(self.optimizer, step)
            error_fn = None
            if self.error_fn is not None and frame.c2w_true is not None:
                error_fn = lambda poses, truth=frame.c2w_true: self.error_fn(poses, truth)  # noqa: E731
            result = optimize_candidates(self.loaded, candidates, observed, frame.intrinsics, sampler, eval_pixels,
                                         self.centre, optimizer, rng, error_fn)
            order = torch.argsort(result.losses)
            best = result.c2w[order[0]].cpu()
            best_loss = float(result.losses[order[0]])
            if mc.mode == "fixed" and records and records[-1].loss <= best_loss:
                # Elitism: a step that finds nothing better keeps the previous estimate (same image).
                best, best_loss = records[-1].estimate, records[-1].loss
            alive = int(torch.isfinite(result.losses).sum())
            if alive == 0:
                raise FloatingPointError(f"every candidate's loss became NaN or infinite at step {step}")
            kept_count = keep_count(mc, step, alive)
            kept = result.c2w[order[:kept_count]].cpu()
            if mc.mode == "trajectory" and mc.motion_prior and records:
                kept = _constant_velocity(records[-1].estimate, best) @ kept
            spawned = perturb_about(kept.repeat_interleave(mc.spawn, 0), self.centre.cpu(), mc.spawn_rot_deg,
                                    mc.spawn_trans_m * scale, generator)
            record = StepRecord(step if mc.mode == "trajectory" else 0, best, best_loss, candidates.shape[0],
                                result, kept_count)
            records.append(record)
            if on_step is not None:
                on_step(record)
            candidates = torch.cat([kept, spawned])
        return records


def _decayed(config: OptimizerConfig, step: int) -> OptimizerConfig:
    """The optimizer settings continuing the learning-rate decay across steps (``reset_lr=False``)."""
    factor = config.lr_decay ** (step * config.iterations / config.lr_decay_iterations)
    return replace(config, lr=config.lr * factor)


def _constant_velocity(previous: Tensor, current: Tensor) -> Tensor:
    """The world-frame motion [4, 4] that took the previous estimate to the current one, applied once more
    predicts the next pose (camera-to-world poses, left multiplication)."""
    motion = current.double() @ torch.linalg.inv(previous.double())
    return exp_se3(log_se3(motion)).float()  # re-orthonormalised through the Lie algebra
