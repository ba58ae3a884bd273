"""The Monte Carlo schedule along a trajectory (thesis section 3.4).

Each Monte Carlo step optimizes the current candidates against one image, ranks them, and keeps the
best few; each kept pose spawns perturbed copies, and kept plus spawned poses start the next step. Frame
``k`` gets ``steps_per_frame`` consecutive steps (:meth:`Tracker.schedule`, the one step loop, which
``ns-invert`` drives too). In ``trajectory`` mode the candidates carry over to the next frame (the thesis'
contribution: the search narrows while the target moves); in ``fixed`` mode every frame starts again from
the starting poses and is inverted alone (parallel iNeRF on each image, the baseline). The best candidate
of a frame's last step is the estimate for that frame.
"""

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3, log_se3, perturb_about
from nerfinv_plugin.inversion.appearance import GainBias
from nerfinv_plugin.inversion.motion_filter import MotionFilter, MotionFilterConfig, MotionState, PoseMeasurement
from nerfinv_plugin.inversion.optimizer import (
    IterationRecord,
    OptimizerConfig,
    PreparedFrame,
    StepResult,
    optimize_candidates,
    outline_loss,
)
from nerfinv_plugin.inversion.sampling import PixelSampler, Strategy
from nerfinv_plugin.inversion.silhouette import Silhouette, edge_mask
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import AS_TRAINED, Intrinsics, RenderSettings, render

Region = Literal["object", "image"]
"""Where pixels are drawn: about the object found in the frame, or anywhere in the image."""


@dataclass
class MonteCarloConfig:
    """How candidates are kept and spawned between steps."""

    mode: Literal["trajectory", "fixed"] = "trajectory"
    """trajectory: the candidates carry over from frame to frame (the thesis' method); fixed: every frame
    starts again from the starting poses, alone (parallel iNeRF on each image, the baseline), its seed the
    run's plus the frame's index and its keep schedule from the first step."""
    keep: tuple[int, ...] = (3, 3)
    """Candidates kept after each step; the last entry repeats. 3 at every step tracked better than the
    thesis' Lego runs' 3, then 1 (docs/benchmarks.md: 29/30 against 27/30 runs under 3 degrees on the toy,
    22/30 against 16/30 under 5 degrees on the spacecraft)."""
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
    motion: Literal["none", "constant-velocity", "filter"] = "none"
    """Trajectory mode: where the next frame's candidates start. none: where this frame's kept candidates
    are; constant-velocity: moved once more by the last frame-to-frame motion of the estimate (amplifies
    the estimates' noise, docs/benchmarks.md); filter: moved together so that the best lands where a Kalman
    filter on SE(3) of the pose about the target predicts the next frame (motion-filter options)."""
    motion_filter: MotionFilterConfig = field(default_factory=MotionFilterConfig)
    """The filter of ``motion filter``."""


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
    object_region: np.ndarray | None = None
    """[H, W] bool: the box of the object found in the frame, widened: where the ranking pixels (and, with
    ``sample_region object``, each iteration's pixels) are drawn, so that most of them tell candidates
    apart. None: the object was not found; pixels come from the whole image."""
    mask: np.ndarray | None = None
    """[H, W] bool: the object as observed, for the silhouette loss. None: no silhouette term here."""
    mask_threshold: float = float("nan")
    """Grey level (0-255) that separated ``mask`` from the background; NaN for a mask given by the user."""

    def region(self, where: Region) -> np.ndarray | None:
        """The pixels [H, W] bool to draw from for ``where``; None: anywhere in the image."""
        return self.object_region if where == "object" else None


@dataclass
class StepRecord:
    """What one Monte Carlo step produced."""

    frame_index: int
    estimate: Tensor
    """[4, 4] best pose of the step (model frame); on a frame seen by the previous step too, the better of
    the two steps' bests."""
    loss: float
    candidates: int
    result: StepResult
    kept: int = 0
    silhouette_weight: float | None = None
    """The silhouette term's weight in the step (``silhouette_trust`` adapts it); None without the term."""
    outline_loss: float | None = None
    """The silhouette loss of ``estimate`` on the frame's ranking band, unweighted (how far the model's outline
    is from the frame's there); None without the term."""


@dataclass
class TrackerState:
    """Everything the next step depends on. Saving it after every step and loading it back continues a run
    with exactly the numbers an uninterrupted run would have produced."""

    step: int
    """Steps taken so far; indexes the keep schedule and the learning-rate decay."""
    candidates: Tensor
    """[N, 4, 4] poses the next step starts from."""
    rng: np.random.Generator
    """Pixel draws."""
    generator: torch.Generator
    """Spawned perturbations."""
    last_frame: int = -1
    last_estimate: Tensor | None = None
    last_loss: float = float("inf")
    previous_estimate: Tensor | None = None
    """Estimate of the frame before ``last_frame``, for ``motion constant-velocity``."""
    eval_pixels: Tensor | None = None
    """The ranking pixels of ``last_frame``: steps on one frame rank on the same pixels."""
    carried: int = 0
    """How many of ``candidates``, from the front, the last step left (kept and spawned); any after them
    joined since (bank hypotheses of the next frame)."""
    motion: MotionState | None = None
    """``motion filter``: the filter after the estimate of ``last_frame``."""
    motion_before: MotionState | None = None
    """``motion filter``: the filter's prediction for ``last_frame``, before its estimate: another step on
    that frame measures it again from here, so a frame counts once however many steps it gets."""
    appearance: GainBias | None = None
    """``appearance gain-bias``: the mapping fitted on ``last_frame``, which its further steps reuse."""
    outline_loss: float | None = None
    """The last step's :attr:`StepRecord.outline_loss`: ``silhouette_trust`` weighs the next step's term by it."""

    def state_dict(self) -> dict:
        return {"step": self.step, "candidates": self.candidates, "rng": self.rng.bit_generator.state,
                "generator": self.generator.get_state(), "last_frame": self.last_frame,
                "last_estimate": self.last_estimate, "last_loss": self.last_loss,
                "previous_estimate": self.previous_estimate, "eval_pixels": self.eval_pixels,
                "carried": self.carried, "motion": None if self.motion is None else self.motion.to_dict(),
                "motion_before": None if self.motion_before is None else self.motion_before.to_dict(),
                "appearance": None if self.appearance is None else self.appearance.to_dict(),
                "outline_loss": self.outline_loss}

    @classmethod
    def from_state_dict(cls, state: dict) -> "TrackerState":
        rng = np.random.default_rng()
        rng.bit_generator.state = state["rng"]
        generator = torch.Generator()
        generator.set_state(state["generator"])
        motion, before = state.get("motion"), state.get("motion_before")  # absent in runs saved before the filter
        return cls(state["step"], state["candidates"], rng, generator, state["last_frame"], state["last_estimate"],
                   state["last_loss"], state["previous_estimate"], state["eval_pixels"], state.get("carried", 0),
                   None if motion is None else MotionState.from_dict(motion),
                   None if before is None else MotionState.from_dict(before),
                   None if state.get("appearance") is None else GainBias.from_dict(state["appearance"]),
                   state.get("outline_loss"))


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
    render: RenderSettings = AS_TRAINED
    """How every render samples rays (``ns-invert``: :func:`nerfinv_plugin.inversion.session.bound_rays`)."""
    sample_region: Region = "image"
    """Where each iteration's pixels are drawn: object: in the frame's ``object_region``; image: anywhere."""
    rank_region: Region = "object"
    """Where the ranking pixels are drawn: object: in the frame's ``object_region``; image: anywhere."""
    object_radius: float | None = None
    """The object's radius in model units, when known: the unit of Adam's translation steps under
    ``translation_unit="object"`` (unknown: one model unit)."""

    def begin(self, start: Tensor, seed: int | None = None) -> TrackerState:
        """The state before the first step, from the candidates ``start`` [N, 4, 4]."""
        seed = self.seed if seed is None else seed
        return TrackerState(0, start.to(torch.float32).cpu(), np.random.default_rng(seed),
                            torch.Generator().manual_seed(seed))

    def step(self, state: TrackerState, frame: Frame, frame_index: int,
             on_iteration: Callable[[int, IterationRecord], None] | None = None) -> StepRecord:
        """One Monte Carlo step against ``frame``: optimize, rank, keep, spawn. Updates ``state`` for the
        next step. Consecutive steps on the same frame are elitist: a step that finds nothing better keeps
        the previous estimate, so the best loss of a frame never increases."""
        mc = self.monte_carlo
        # Gauss-Newton keeps one draw for the whole step: from the object's box, where the residuals say something
        region = "object" if self.optimizer.method == "gauss-newton" else self.sample_region
        sampler = PixelSampler(self.sampling, self.pixels).prepare(frame.image, frame.region(region))
        same_frame = state.last_frame == frame_index
        if mc.mode == "trajectory" and mc.motion == "filter" and not same_frame:
            self._predict(state, frame_index)
        if same_frame:
            eval_pixels = state.eval_pixels
        else:
            eval_pixels = torch.as_tensor(
                PixelSampler("random", self.eval_pixels).prepare(frame.image, frame.region(self.rank_region))
                .sample(state.rng))
        optimizer = self.optimizer if mc.reset_lr or state.step == 0 else _decayed(self.optimizer, state.step)
        optimizer = _trusted(optimizer, state.outline_loss)
        error_fn = None
        if self.error_fn is not None and frame.c2w_true is not None:
            error_fn = lambda poses, truth=frame.c2w_true: self.error_fn(poses, truth)  # noqa: E731
        silhouette = None
        if (optimizer.silhouette_weight > 0 or (optimizer.rank_silhouette_weight or 0) > 0) and frame.mask is not None:
            mask, level = frame.mask, None
            if optimizer.silhouette_from == "grey" and not math.isnan(frame.mask_threshold):
                mask, level = edge_mask(frame.image, frame.mask, frame.mask_threshold, optimizer.silhouette_edge)
            silhouette = Silhouette.from_mask(mask, optimizer.silhouette_band_px, optimizer.silhouette_pixels,
                                              optimizer.silhouette_weight, self.loaded.device, level,
                                              optimizer.silhouette_softness)
        appearance = None
        if optimizer.appearance == "gain-bias":
            appearance = state.appearance if same_frame else self._fit_appearance(state.candidates[0], frame,
                                                                                 eval_pixels)
        prepared = PreparedFrame.from_image(self.loaded, frame.image, frame.intrinsics, sampler, eval_pixels,
                                            self.centre, error_fn, silhouette, appearance)
        length = self.object_radius if optimizer.translation_unit == "object" and self.object_radius else 1.0
        result = optimize_candidates(self.loaded, state.candidates, prepared, optimizer, state.rng, on_iteration,
                                     min_candidates=keep_count(mc, state.step, state.candidates.shape[0]),
                                     settings=self.render, length=length)
        alive = int(torch.isfinite(result.losses).sum())
        if alive == 0:
            raise FloatingPointError(f"every candidate's loss became NaN or infinite on frame "
                                     f"{frame.name or frame_index}")
        order = torch.argsort(result.losses)
        best = result.c2w[order[0]].cpu()
        best_loss = float(result.losses[order[0]])
        if same_frame and state.last_loss <= best_loss:
            best, best_loss = state.last_estimate, state.last_loss
        kept_count = keep_count(mc, state.step, alive)
        kept = result.c2w[order[:kept_count]].cpu()
        previous = state.previous_estimate if same_frame else state.last_estimate
        if mc.mode == "trajectory" and mc.motion == "constant-velocity" and previous is not None:
            kept = _constant_velocity(previous, best) @ kept
        if mc.mode == "trajectory" and mc.motion == "filter":
            self._measure(state, best, kept, result.losses[order[:kept_count]].cpu())
        spawned = perturb_about(kept.repeat_interleave(mc.spawn, 0), self.centre.cpu(), mc.spawn_rot_deg,
                                mc.spawn_trans_m * self.loaded.dataparser_scale, state.generator)
        outline = None
        if silhouette is not None:
            outline = outline_loss(self.loaded, best, frame.intrinsics, silhouette.band(silhouette.eval_pixels),
                                   self.render)
        record = StepRecord(frame_index, best, best_loss, state.candidates.shape[0], result, kept_count,
                            None if silhouette is None else optimizer.silhouette_weight, outline)
        state.previous_estimate = previous
        state.step += 1
        state.candidates = torch.cat([kept, spawned])
        state.carried = state.candidates.shape[0]
        state.last_frame, state.last_estimate, state.last_loss = frame_index, best, best_loss
        state.eval_pixels = eval_pixels
        state.appearance = appearance
        state.outline_loss = outline if outline is not None else state.outline_loss
        return record

    def _fit_appearance(self, c2w: Tensor, frame: Frame, pixels: Tensor) -> GainBias:
        """The frame's gain and bias, fitted on ``pixels`` [P, 2] with the model rendered at ``c2w`` [4, 4]."""
        with torch.no_grad():
            rendered = render(self.loaded, c2w[None], frame.intrinsics, pixels, self.render).rgb[0]
        observed = torch.as_tensor(frame.image[pixels[:, 0].numpy(), pixels[:, 1].numpy()], dtype=torch.float32)
        return GainBias.fit(rendered, observed / 255.0)

    def _motion_filter(self) -> tuple[MotionFilter, Tensor]:
        """The filter in model units, and the transform [4, 4] float64 from the model frame to the target's."""
        to_target = torch.eye(4, dtype=torch.float64)
        to_target[:3, 3] = -self.centre.double().cpu()
        return MotionFilter(self.monte_carlo.motion_filter, self.loaded.dataparser_scale), to_target

    def _predict(self, state: TrackerState, frame_index: int) -> None:
        """Before the first step on ``frame_index``: the filter's prediction for it, and the candidates the
        last step carried over moved together (one rigid motion) so that the last frame's estimate lands on
        it. Candidates that joined since (bank hypotheses of this frame) stay where they are."""
        state.motion_before = None
        if state.motion is None:
            return
        frames = frame_index - state.last_frame
        assert frames >= 1, (frame_index, state.last_frame)  # the schedule only goes forward
        motion_filter, to_target = self._motion_filter()
        state.motion_before = motion_filter.predict(state.motion, frames)
        move = torch.linalg.inv(to_target) @ state.motion_before.pose @ torch.linalg.inv(state.last_estimate.double())
        carried = state.candidates[:state.carried].double()
        state.candidates = torch.cat([(move @ carried).float(), state.candidates[state.carried:]])

    def _measure(self, state: TrackerState, best: Tensor, kept: Tensor, losses: Tensor) -> None:
        """The filter told the frame's estimate ``best`` [4, 4], its uncertainty from the ``kept`` candidates
        [K, 4, 4] and their ``losses`` [K]; from the frame's prediction, so that a frame measured again by a
        later step on it counts once."""
        motion_filter, to_target = self._motion_filter()
        best_t = to_target @ best.double()
        covariance = motion_filter.fit_covariance(best_t, to_target @ kept.double(), losses)
        state.motion, _ = motion_filter.update(state.motion_before, PoseMeasurement(best_t, covariance))

    def schedule(self, frames: int | Iterable[int], start: Tensor, steps_per_frame: int = 1,
                 state: TrackerState | None = None, done: int = 0) -> Iterator[tuple[int, int, int, TrackerState]]:
        """The one step loop: ``(step index, frame index, step within the frame, state)`` for each step from
        step ``done`` on (a resumed run passes its saved ``state``), the caller taking the step
        (:meth:`step`) before asking for the next. ``frames`` is the order the frames are taken in, each
        getting ``steps_per_frame`` consecutive steps: a count ``n`` is every frame in turn, ``range(n)``;
        an iterable may decide each frame when it is asked for, after the steps before it were taken (the
        realtime clock, :meth:`nerfinv_plugin.inversion.clock.Clock.visits`). In fixed mode each frame's
        first step starts from ``start`` again, seeded ``seed + k``."""
        if state is None:
            state = self.begin(start)
        order = range(frames) if isinstance(frames, int) else frames
        step_index = 0
        for k in order:
            for within in range(steps_per_frame):
                if step_index >= done:
                    if within == 0 and self.monte_carlo.mode == "fixed":
                        state = self.begin(start, seed=self.seed + k)
                    yield step_index, k, within, state
                step_index += 1

    def run(self, frames: Sequence[Frame], start: Tensor, steps_per_frame: int = 1) -> list[StepRecord]:
        """Every step of :meth:`schedule` over ``frames`` from the candidates ``start`` [N, 4, 4], without
        the run folder, detections or bank of ``ns-invert`` (tests, benchmarks)."""
        return [self.step(state, frames[k], k) for _, k, _, state in self.schedule(len(frames), start,
                                                                                   steps_per_frame)]


def _decayed(config: OptimizerConfig, step: int) -> OptimizerConfig:
    """The optimizer settings continuing the learning-rate decay across steps (``reset_lr=False``)."""
    factor = config.lr_decay ** (step * config.iterations / config.lr_decay_iterations)
    return replace(config, lr=config.lr * factor)


def _constant_velocity(previous: Tensor, current: Tensor) -> Tensor:
    """The world-frame motion [4, 4] that took the previous estimate to the current one, applied once more
    predicts the next pose (camera-to-world poses, left multiplication)."""
    motion = current.double() @ torch.linalg.inv(previous.double())
    return exp_se3(log_se3(motion)).float()  # re-orthonormalised through the Lie algebra


def _trusted(config: OptimizerConfig, outline: float | None) -> OptimizerConfig:
    """``config`` with its silhouette weight times ``min(1, silhouette_trust / outline)**2``, ``outline`` the
    last step's outline loss (:attr:`OptimizerConfig.silhouette_trust`); as it is without a trust level or an
    outline loss yet (the first step)."""
    if config.silhouette_trust is None or outline is None or outline <= config.silhouette_trust:
        return config
    return replace(config, silhouette_weight=config.silhouette_weight * (config.silhouette_trust / outline) ** 2)
