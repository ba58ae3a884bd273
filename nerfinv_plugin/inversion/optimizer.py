"""Optimizing N candidate poses in parallel against one observed image (thesis section 3.3).

Each candidate is ``T = C exp([S] theta) C^-1 T0``: screw coordinates ``theta`` (angular part first)
act on the start pose ``T0`` about the point ``C`` (the target centre by default, so a rotation turns the
camera around the target instead of swinging the target out of view; ``screw_origin="world"`` gives the
thesis' plain ``exp([S] theta) T0`` about the model-frame origin). The translation part of ``theta`` is in
units of the object's radius by default: Adam moves every coordinate by about its learning rate whatever
the gradient's size, so in model units the step sizes would depend on the scale the dataparser gave the
scene (``translation_unit``). All candidates' rays go through the
model in chunked batches; each chunk's loss is back-propagated before the next is rendered, and the
accumulated pose gradient is pushed into ``theta`` once per iteration. Adam, exponentially decaying
learning rate.

A step is a :class:`PreparedFrame` (what the observed frame gives every iteration: its colours, camera,
pixel sampler, ranking pixels and target centre) and a :class:`CandidateStep` (the state the iterations
advance); :func:`optimize_candidates` runs one over the other.
"""

import copy
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3
from nerfinv_plugin.inversion.appearance import GainBias, fit_each
from nerfinv_plugin.inversion.losses import LossName, per_candidate_loss, per_ray_loss
from nerfinv_plugin.inversion.sampling import PixelSampler
from nerfinv_plugin.inversion.silhouette import BandPixels, Silhouette, silhouette_per_ray, soft_grey
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import AS_TRAINED, Intrinsics, RenderOutput, RenderSettings, render, render_chunks


@dataclass
class OptimizerConfig:
    """Gradient descent on the candidates of one Monte Carlo step."""

    method: Literal["adam", "gauss-newton"] = "adam"
    """adam: gradient steps on fresh pixels every iteration (the thesis); gauss-newton: damped Gauss-Newton
    (Levenberg-Marquardt) steps on the mean squared colour error of pixels in the object's box, coarse to
    fine through levels of blur, each step kept only when it lowers the loss: it does not random-walk along
    the weakly observable direction (:mod:`nerfinv_plugin.inversion.gauss_newton`; mse, no silhouette)."""
    iterations: int = 60
    """Adam iterations per Monte Carlo step (the thesis used 60)."""
    gauss_newton_blur_px: tuple[float, ...] = (4.0, 2.0, 0.0)
    """Gauss-Newton: the levels of blur, coarse to fine (Gaussian sigma in pixels of the working resolution);
    0 compares sharp pixels, one ray each."""
    gauss_newton_rays_per_pixel: int = 8
    """Gauss-Newton: rays jittered about each pixel of a blurred level, whose mean colour is compared."""
    gauss_newton_iterations: int = 6
    """Gauss-Newton: trial steps per level at most (each renders once, with three backward passes), after the
    level's first render; a candidate whose steps keep failing stops earlier."""
    lr: float = 0.01
    """Adam learning rate at the start of each step (the thesis' 0.01)."""
    lr_decay: float = 0.8
    """Multiplies the learning rate every ``lr_decay_iterations`` iterations, smoothly (iNeRF's 0.8)."""
    lr_decay_iterations: int = 20
    averaging: float = 0.0
    """Adam: the step ends at an exponential moving average of each candidate's iterates (its screw
    coordinates) with this weight on the past, instead of at its last iterate (Polyak averaging; 0.9 averages
    about the last 10 iterations). Adam on fresh pixels each iteration jitters about the minimum and walks along
    flat directions; the average keeps the jitter out of the estimate. 0: off (the thesis)."""
    loss: LossName = "mse"
    """Photometric loss: mse (thesis), mape (Parallel Inversion) or huber."""
    colour_weight: float = 1.0
    """Factor on the photometric loss; 0 with a silhouette weight optimizes the silhouette alone."""
    silhouette_weight: float = 0.25
    """Factor on the silhouette loss (the model's silhouette against the observed object mask, on a band
    about its outline: :mod:`nerfinv_plugin.inversion.silhouette`), added to the photometric loss. 0: off.
    With ``silhouette_from grey`` cut at ``silhouette_edge 0.35``, 0.25 ended 33% of the frames of the unseen
    seed-23 counts (ten seeds) under 5 degrees against 20% off, and 108 of 120 frames of user-path.sh's model
    over three seeds against 98 (docs/benchmarks.md, session 15)."""
    rank_silhouette_weight: float | None = None
    """Factor on the silhouette loss when the step's candidates are ranked (which one is the frame's estimate
    and which go on); unset: ``silhouette_weight``, which then weighs both. 0 ranks on colour, as the thesis
    does. Side by side over 1,200 frames of unseen scenes (session 20, docs/benchmarks.md), 0 ended more runs
    under 5 degrees on their last frame (145 against 137 of 150) but had fewer frames under 5 degrees (76.7%
    against 80.7%), so the default stays unset."""
    silhouette_trust: float | None = None
    """The outline loss (the silhouette term's band mean, unweighted) up to which the model's outline counts as
    matching the frame's. Above it the step's silhouette weight (optimization's and, unless set apart, the
    ranking's) is ``silhouette_weight x (silhouette_trust / L)**2``, ``L`` the outline loss of the last step's
    estimate, so that a model whose outline cannot match the frames' (a fuzz along thin edges close in, a
    panel it renders dim: docs/benchmarks.md) pulls less. The square, because the estimate's ``L``
    understates the misfit (the term has already pulled the estimate's outline onto the frame's) and a weight
    of 0.05 was measured to help where 0.1 did not (session 24). Unset: the weight is fixed. Frames of
    well-modelled scenes end at 0.03-0.07."""
    silhouette_from: Literal["accumulation", "grey"] = "grey"
    """What the model's silhouette is. accumulation: its opacity along each ray. grey: its rendered colour
    as the detector reads a frame (the maximum over channels), through a sigmoid centred on the grey level
    that frame's object was cut at (``silhouette_edge``), ``silhouette_softness`` levels wide; where the mask
    came from the user (no grey level) the accumulation. A model trained on a black background may leave its dark parts
    transparent, since black there costs nothing: its accumulation is then smaller than the object the
    detector finds, and the term pulls candidates nearer than the truth (docs/benchmarks.md)."""
    silhouette_edge: float = 0.35
    """grey: both silhouettes, the frame's and the model's, are cut at this fraction of the object's median grey
    level in the frame (at least the detector's threshold), nearer the middle of its edges. The model blurs
    the outline; cut at the detector's low threshold its silhouette is larger than the frame's, and the term
    put the range 4-6% too far at the true attitude (docs/benchmarks.md, session 15). At 0.5 dark faces and
    texture fell below the level too and tracking got worse. 0: the detector's threshold."""
    silhouette_softness: float = 4.0
    """grey: the sigmoid's scale, in grey levels (0-255)."""
    silhouette_pixels: int = 128
    """Band pixels drawn per iteration for the silhouette loss, besides the photometric pixels."""
    silhouette_band_px: int = 3
    """Half-width of the band about the observed outline the silhouette pixels come from, in pixels."""
    appearance: Literal["as-observed", "gain-bias", "candidate-gain-bias"] = "as-observed"
    """as-observed: compare the observed colours as they are; gain-bias: map them to the model's scale with a
    per-channel gain and bias fitted once per frame at the best starting candidate (another camera, exposure
    or light than the training images': :mod:`nerfinv_plugin.inversion.appearance`); candidate-gain-bias:
    every candidate's render mapped to the frame by a gain and bias of its own, refitted each iteration."""
    translation_unit: Literal["object", "model"] = "object"
    """What one unit of the screw's translation part is. object: the object's radius, so that a step moves
    the object in the image about as far as a turn of the same size does, on any scene scale. model: one
    model unit (the thesis). On nerfstudio-data scenes (scaled into the unit cube, a 0.9 m spacecraft is
    0.17 units) a model-unit step moved the object five times farther than a turn did, and Adam's noisy
    steps walked candidates 30-45 pixels off the object within one step (docs/benchmarks.md). Gauss-Newton
    solves for its steps and takes no unit."""
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
    polish_iterations: int = 20
    """Adam: after the ranking, this many more iterations on the step's best candidate alone, on the colour loss
    only, with ``polish_pixels`` fresh pixels each, from ``polish_lr``; it replaces the best candidate. The
    silhouette term holds the runs but its minimum lies 1.4-4 degrees off the truth along the weak direction,
    the colour's nearer: on unseen scenes 20 ended 71 of 90 runs under 5 degrees against 68, median final 2.48
    against 2.91 degrees, at 1.17x the time per frame (docs/benchmarks.md, session 27). 0: off; none with
    Gauss-Newton or a colour weight of 0."""
    polish_pixels: int = 1024
    """Colour pixels each polishing iteration draws (where the step's pixels are drawn)."""
    polish_lr: float = 0.003
    """Adam learning rate at the start of the polish (decaying as the step's does)."""


@dataclass(frozen=True)
class IterationRecord:
    """One gradient iteration of a step, as the history keeps it."""

    loss: np.ndarray
    """[N] loss of every candidate on the iteration's pixels; ``inf`` for dropped and pruned candidates."""
    error_deg: np.ndarray | None = None
    """[N] rotation error of every candidate (degrees) at the poses the loss was measured at, when the
    truth is known."""
    c2w: np.ndarray | None = None
    """[N, 4, 4] the poses the loss was measured at (model frame): what the viewer and the run's candidate
    trail draw."""


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


def centred(centre: Tensor) -> tuple[Tensor, Tensor]:
    """The translations [4, 4] to and from ``centre`` [3]: a screw turns about it as ``C exp([S] theta) C^-1``."""
    to_centre = torch.eye(4, dtype=centre.dtype, device=centre.device)
    to_centre[:3, 3] = centre
    from_centre = torch.eye(4, dtype=centre.dtype, device=centre.device)
    from_centre[:3, 3] = -centre
    return to_centre, from_centre


def model_silhouette(loaded: LoadedModel, out: RenderOutput, band: BandPixels) -> Tensor:
    """The model's silhouette on rendered rays, as ``band`` reads it: their accumulation, or with the band's
    grey level their colour through :func:`soft_grey`. Raises for a model without accumulation that needs it."""
    if band.threshold is not None:
        return soft_grey(out.rgb, band.threshold, band.softness)
    if out.accumulation is None:
        raise ValueError(f"{type(loaded.model).__name__} gives no accumulation output: the silhouette "
                         "loss cannot be used with it (set --optimizer.silhouette-weight 0)")
    return out.accumulation


def candidate_losses(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor, observed: Tensor,
                     loss: LossName, backward: bool, settings: RenderSettings = AS_TRAINED,
                     band: BandPixels | None = None, colour_weight: float = 1.0,
                     mapping: tuple[Tensor, Tensor] | None = None, rendered: Tensor | None = None) -> Tensor:
    """Loss of each candidate [N]: ``colour_weight`` times the mean photometric loss over ``pixels``, plus,
    with ``band``, its weight times the mean silhouette loss over the band pixels, all rendered in one pass
    under ``settings``. With ``backward``, gradients accumulate into ``c2w.grad`` chunk by chunk, so memory
    stays bounded by one chunk. ``mapping``, each candidate's gain and bias [N, 3] (``candidate-gain-bias``),
    maps its rendered colours to the frame's before they are compared; ``rendered`` [N, P, 3], when given,
    receives the colours each candidate rendered at ``pixels`` (detached, before the mapping)."""
    n, p = c2w.shape[0], pixels.shape[0]
    colour_rays = p
    totals = torch.zeros(n, dtype=torch.float32, device=loaded.device)
    colour_scale = torch.full((p,), colour_weight / p, device=loaded.device)
    if band is not None:  # band rays follow the colour rays; their colour is not compared
        b = band.pixels.shape[0]
        pixels = torch.cat([pixels, band.pixels.to(pixels.device)])
        observed = torch.cat([observed, torch.zeros(b, 3, device=observed.device, dtype=observed.dtype)])
        colour_scale = torch.cat([colour_scale, torch.zeros(b, device=loaded.device)])
        band_scale = torch.cat([torch.zeros(p, device=loaded.device), torch.full((b,), band.weight / b,
                                                                                 device=loaded.device)])
        inside = torch.cat([torch.zeros(p, device=loaded.device), band.inside.to(loaded.device)]).repeat(n)
        band_scale = band_scale.repeat(n)
        p += b
    targets = observed.repeat(n, 1)
    colour_scale = colour_scale.repeat(n)
    candidate_of_ray = torch.arange(n, device=loaded.device).repeat_interleave(p)
    every_ray = None if rendered is None else torch.zeros(n * p, 3, device=loaded.device)
    with torch.set_grad_enabled(backward):
        for part, out in render_chunks(loaded, c2w, intrinsics, pixels, settings):
            rgb = out.rgb
            if every_ray is not None:
                every_ray[part] = rgb.detach()
            if mapping is not None:
                of = candidate_of_ray[part]
                rgb = rgb * mapping[0][of] + mapping[1][of]
            per_ray = per_ray_loss(loss, rgb, targets[part]) * colour_scale[part]
            if band is not None:
                per_ray = per_ray + silhouette_per_ray(model_silhouette(loaded, out, band),
                                                       inside[part]) * band_scale[part]
            if backward and per_ray.requires_grad:  # rays that missed the target carry no gradient
                # Non-finite rays must not poison the others' gradients; their candidates get dropped. Every
                # chunk's graph starts in the one ray bundle built from c2w for all rays: it is kept for the
                # next chunk's backward (retain_graph), and the chunk's own part goes with ``out`` below.
                torch.where(torch.isfinite(per_ray), per_ray, 0.0).sum().backward(retain_graph=True)
            totals.index_add_(0, candidate_of_ray[part], per_ray.detach())
            del out, rgb, per_ray  # before the next chunk renders: one chunk's graph in memory at a time
    if rendered is not None:
        rendered.copy_(every_ray.reshape(n, p, 3)[:, :colour_rays])
    return totals


def outline_loss(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, band: BandPixels,
                 settings: RenderSettings = AS_TRAINED) -> float:
    """The silhouette loss of one pose ``c2w`` [4, 4] on ``band``'s pixels, unweighted: how far the model's
    outline there is from the frame's (0: it matches to the pixel; the soft edge leaves about 0.03)."""
    with torch.no_grad():
        out = render(loaded, c2w[None].to(loaded.device, torch.float32), intrinsics, band.pixels, settings)
    return float(silhouette_per_ray(model_silhouette(loaded, out, band), band.inside.to(loaded.device)).mean())


@dataclass(frozen=True)
class PreparedFrame:
    """One observed frame made ready for a step: what every iteration and the final ranking read. Built
    once per step by :meth:`from_image`; the iterations only draw pixels from it."""

    observed: Tensor
    """[H, W, 3] float32 in [0, 1] on the model's device."""
    intrinsics: Intrinsics
    sampler: PixelSampler
    """Prepared on the observed image; draws fresh pixels each iteration, shared by all candidates."""
    eval_pixels: Tensor
    """[E, 2] (row, col), fixed for the frame, so that candidates (and steps) are ranked on the same pixels."""
    centre: Tensor
    """[3] target centre in the model frame, on the model's device: screw motions turn about it."""
    error_fn: Callable[[Tensor], Tensor] | None = None
    """Poses [N, 4, 4] to rotation errors in degrees [N], recorded in the history when the truth is known."""
    silhouette: Silhouette | None = None
    """The observed object mask's band, when the silhouette loss (optimization's or ranking's) is on and the
    frame has a mask."""

    @classmethod
    def from_image(cls, loaded: LoadedModel, image: np.ndarray | Tensor, intrinsics: Intrinsics,
                   sampler: PixelSampler, eval_pixels: Tensor, centre: Tensor,
                   error_fn: Callable[[Tensor], Tensor] | None = None,
                   silhouette: Silhouette | None = None, appearance: GainBias | None = None) -> "PreparedFrame":
        """From the observed ``image`` [H, W, 3] ``uint8`` RGB, mapped to the model's scale by ``appearance``."""
        observed = torch.as_tensor(image, dtype=torch.float32, device=loaded.device) / 255.0
        if appearance is not None:
            observed = appearance.to_model(observed)
        return cls(observed, intrinsics, sampler, torch.as_tensor(eval_pixels).to(loaded.device),
                   centre.to(loaded.device, torch.float32), error_fn, silhouette)

    def colours(self, pixels: Tensor) -> Tensor:
        """Observed colours [P, 3] at ``pixels`` [P, 2]."""
        return self.observed[pixels[:, 0], pixels[:, 1]]


class CandidateStep:
    """The optimization of N candidates over one step, an iteration at a time: screw parameters ``theta``
    [N, 6] on the start poses, Adam with its decaying learning rate, and which candidates go on."""

    def __init__(self, loaded: LoadedModel, start: Tensor, frame: PreparedFrame, config: OptimizerConfig,
                 min_candidates: int = 1, settings: RenderSettings = AS_TRAINED, length: float = 1.0):
        device = loaded.device
        self.loaded, self.frame, self.config, self.min_candidates = loaded, frame, config, min_candidates
        self.settings = settings
        self.start = start.to(device, torch.float32)
        n = self.start.shape[0]
        self.theta = torch.zeros(n, 6, device=device, requires_grad=True)
        self.average = torch.zeros(n, 6, device=device)
        """Exponential moving average of ``theta`` over the iterations (``config.averaging``)."""
        self.units = torch.tensor([1.0, 1.0, 1.0, length, length, length], device=device)
        """What one unit of each screw coordinate is: radians, then ``length`` model units."""
        if config.screw_origin == "target":
            self.to_centre, self.from_centre = centred(frame.centre.to(device, torch.float32))
        else:
            self.to_centre, self.from_centre = torch.eye(4, device=device), torch.eye(4, device=device)
        self.optimizer = torch.optim.Adam([self.theta], lr=config.lr)
        gamma = config.lr_decay ** (1.0 / config.lr_decay_iterations)
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma=gamma)
        self.alive = torch.ones(n, dtype=torch.bool, device=device)
        """Not dropped for a non-finite pose, loss or gradient."""
        self.active = self.alive.clone()
        """Alive and not pruned: still rendered and optimized."""
        self.mapping: tuple[Tensor, Tensor] | None = None
        """candidate-gain-bias: each candidate's gain and bias [N, 3], from its last iteration's render."""
        if config.appearance == "candidate-gain-bias":
            self.mapping = torch.ones(n, 3, device=device), torch.zeros(n, 3, device=device)
        self.history: list[IterationRecord] = []
        self.stopped = False
        """No candidate is left, or patience ran out: the step ends before its last iteration."""
        self._best_seen, self._stalled = float("inf"), 0

    def poses(self, theta: Tensor | None = None) -> Tensor:
        """Candidates [N, 4, 4] at screw coordinates ``theta`` (unset: the current ones): ``C exp([S] theta) C^-1
        T0``."""
        theta = self.theta if theta is None else theta
        return self.to_centre @ exp_se3(theta * self.units) @ self.from_centre @ self.start

    def iterate(self, rng: np.random.Generator) -> IterationRecord:
        """One iteration on fresh pixels drawn with ``rng``: render the active candidates, take an Adam
        step, then drop, prune or stop. Returns the iteration's history record."""
        device, config, active = self.loaded.device, self.config, self.active
        pixels = torch.as_tensor(self.frame.sampler.sample(rng), device=device)
        silhouette = self.frame.silhouette
        band = None if silhouette is None or config.silhouette_weight == 0 else silhouette.draw(rng)
        c2w = self.poses()
        rendered = torch.nonzero(active).flatten()
        leaf = c2w[rendered].detach().requires_grad_(True)
        losses = torch.full((c2w.shape[0],), torch.inf, device=device)
        observed = self.frame.colours(pixels)
        mapping = colours = None
        if self.mapping is not None:
            mapping = self.mapping[0][rendered], self.mapping[1][rendered]
            colours = torch.zeros(rendered.shape[0], pixels.shape[0], 3, device=device)
        losses[rendered] = candidate_losses(self.loaded, leaf, self.frame.intrinsics, pixels, observed, config.loss,
                                            backward=True, settings=self.settings, band=band,
                                            colour_weight=config.colour_weight, mapping=mapping, rendered=colours)
        if self.mapping is not None:
            self.mapping[0][rendered], self.mapping[1][rendered] = fit_each(colours, observed)
        grad = torch.zeros_like(c2w)
        grad[rendered] = leaf.grad
        # A pose, loss or gradient that is not finite ends the candidate. nerfstudio's renderer turns NaN
        # colours into 0 in eval mode, so a NaN pose alone would still get a finite loss.
        finite = torch.isfinite(losses) & torch.isfinite(c2w).flatten(1).all(1) & torch.isfinite(grad).flatten(1).all(1)
        self.alive &= ~active | finite
        active &= self.alive
        self.optimizer.zero_grad(set_to_none=True)
        c2w.backward(torch.where(active[:, None, None], grad, 0.0))
        self.optimizer.step()
        self.scheduler.step()
        with torch.no_grad():
            weight = torch.where(active, config.averaging, 1.0)[:, None]  # a pruned candidate's average stays
            self.average.mul_(weight).add_((1.0 - weight) * self.theta.detach())
        losses = torch.where(active, losses, torch.inf)
        error = None if self.frame.error_fn is None else self.frame.error_fn(c2w.detach()).cpu().numpy()
        record = IterationRecord(losses.cpu().numpy(), error, c2w.detach().cpu().numpy())
        self.history.append(record)
        self._after(losses)
        return record

    def _after(self, losses: Tensor) -> None:
        """End the step when nothing is left; prune on schedule; count the iterations without progress."""
        config = self.config
        if not bool(self.active.any()):
            self.stopped = True
            return
        if config.prune_every and len(self.history) % config.prune_every == 0:
            self.active &= ~_far_above_best(losses, config.prune_ratio, self.min_candidates)
        best = float(losses.min())
        self._stalled = 0 if best < self._best_seen * (1.0 - config.min_improvement) else self._stalled + 1
        self._best_seen = min(self._best_seen, best)
        if config.patience is not None and self._stalled >= config.patience:
            self.stopped = True

    def final_poses(self) -> Tensor:
        """Where the step ends [N, 4, 4]: the averaged iterates with ``config.averaging``, else the last."""
        return self.poses(self.average if self.config.averaging > 0 else None).detach()

    def result(self) -> StepResult:
        """The final poses (the averaged iterates with ``config.averaging``) ranked on the frame's evaluation
        pixels."""
        return rank(self.loaded, self.final_poses(), self.alive, self.active, self.frame, self.config, self.settings,
                    self.history)


def rank(loaded: LoadedModel, final: Tensor, alive: Tensor, active: Tensor, frame: PreparedFrame,
         config: OptimizerConfig, settings: RenderSettings, history: list[IterationRecord]) -> StepResult:
    """A step's result: the ``final`` poses [N, 4, 4] of the ``active`` candidates ranked on the frame's
    evaluation pixels (the others' loss is ``inf``); a candidate whose loss there is not finite joins the
    dropped ones (not ``alive``), the alive ones no longer active are the pruned ones. Updates ``alive``."""
    losses = torch.full((final.shape[0],), torch.inf, device=loaded.device)
    kept = torch.nonzero(active).flatten()
    pixels, silhouette = frame.eval_pixels, frame.silhouette
    weight = config.silhouette_weight if config.rank_silhouette_weight is None else config.rank_silhouette_weight
    band = None
    if silhouette is not None and weight > 0:
        band = replace(silhouette.band(silhouette.eval_pixels), weight=weight)
    observed = frame.colours(pixels)
    if config.appearance == "candidate-gain-bias":
        # One render: the silhouette part as it is, the colours kept, then each candidate's own mapping fitted
        # on these very pixels and its colour loss taken from the same colours.
        colours = torch.zeros(kept.shape[0], pixels.shape[0], 3, device=loaded.device)
        silhouette_part = candidate_losses(loaded, final[kept], frame.intrinsics, pixels, observed, config.loss,
                                           backward=False, settings=settings, band=band, colour_weight=0.0,
                                           rendered=colours)
        gain, bias = fit_each(colours, observed)
        mapped = colours * gain[:, None] + bias[:, None]
        losses[kept] = silhouette_part + config.colour_weight * per_candidate_loss(config.loss, mapped, observed)
    else:
        losses[kept] = candidate_losses(loaded, final[kept], frame.intrinsics, pixels, observed, config.loss,
                                        backward=False, settings=settings, band=band,
                                        colour_weight=config.colour_weight)
    alive &= ~active | torch.isfinite(losses)
    losses = torch.where(active & alive, losses, torch.inf)
    dropped = torch.nonzero(~alive).flatten().tolist()
    pruned = torch.nonzero(alive & ~active).flatten().tolist()
    return StepResult(final, losses, history, dropped, pruned)


def optimize_candidates(loaded: LoadedModel, start: Tensor, frame: PreparedFrame, config: OptimizerConfig,
                        rng: np.random.Generator, on_iteration: Callable[[int, IterationRecord], None] | None = None,
                        min_candidates: int = 1, settings: RenderSettings = AS_TRAINED,
                        length: float = 1.0) -> StepResult:
    """Optimize candidates ``start`` [N, 4, 4] against the prepared ``frame`` for at most
    ``iterations_per_step(config)`` iterations, rendering under ``settings``, drawing each iteration's pixels
    with ``rng``; Adam's translation steps are in units of ``length`` (model units). ``on_iteration(i,
    record)`` sees each iteration's history record as it is made (progress bars). Pruning never leaves
    fewer than ``min_candidates``. ``config.method`` picks Adam or Gauss-Newton."""
    if config.method == "gauss-newton":
        from nerfinv_plugin.inversion.gauss_newton import GaussNewtonStep  # it builds on this module's records

        step = GaussNewtonStep(loaded, start, frame, config, min_candidates, settings)
    else:
        step = CandidateStep(loaded, start, frame, config, min_candidates, settings, length)
    for iteration in range(iterations_per_step(config)):
        record = step.iterate(rng)
        if on_iteration is not None:
            on_iteration(iteration, record)
        if step.stopped:
            break
    result = step.result()
    if config.method == "adam" and config.polish_iterations > 0 and config.colour_weight > 0:
        result = polished(loaded, result, frame, config, rng, settings, length)
    return result


def polished(loaded: LoadedModel, result: StepResult, frame: PreparedFrame, config: OptimizerConfig,
             rng: np.random.Generator, settings: RenderSettings, length: float) -> StepResult:
    """``result`` with its best candidate moved by ``config.polish_iterations`` Adam iterations of its own on the
    colour loss alone, ``config.polish_pixels`` fresh pixels each; the other candidates and every loss as they
    were (the best stays first in the ranking)."""
    if not bool(torch.isfinite(result.losses).any()):
        return result
    best = int(torch.argmin(result.losses))
    sampler = copy.copy(frame.sampler)
    sampler.count = config.polish_pixels
    colour_only = replace(config, silhouette_weight=0.0, lr=config.polish_lr, iterations=config.polish_iterations,
                          patience=None, prune_every=None)
    step = CandidateStep(loaded, result.c2w[best][None], replace(frame, sampler=sampler, silhouette=None),
                         colour_only, 1, settings, length)
    for _ in range(config.polish_iterations):
        step.iterate(rng)
        if step.stopped:
            return result
    c2w = result.c2w.clone()
    c2w[best] = step.final_poses()[0]
    return replace(result, c2w=c2w)


def iterations_per_step(config: OptimizerConfig) -> int:
    """The most iterations (renders) one step of ``config.method`` runs."""
    if config.method == "gauss-newton":
        return len(config.gauss_newton_blur_px) * (config.gauss_newton_iterations + 1)
    return config.iterations


def _far_above_best(losses: Tensor, ratio: float, keep: int) -> Tensor:
    """Candidates [N] (bool) whose loss is more than ``ratio`` times the best, sparing the ``keep`` best."""
    far = losses > ratio * losses.min()
    far[torch.argsort(losses)[:keep]] = False
    return far & torch.isfinite(losses)
