"""Damped Gauss-Newton (Levenberg-Marquardt), coarse to fine, on the candidates of one step: the alternative
to Adam that does not random-walk along the weakly observable direction and has a wider basin.

Adam scales every screw coordinate by its own gradient history, so a direction the image hardly constrains
(a small turn about the target plus the shift that keeps the object in place) still gets full-size steps,
and the steps follow the noise of the pixel draws: started on the truth it wanders off by several degrees
(docs/benchmarks.md). Here every iteration solves the normal equations of the colour residuals on a fixed
set of pixels, ``(J^T J + lambda diag(J^T J)) delta = -J^T r``, so a direction moves in proportion to what
the residuals say about it, and a step is kept only when it lowers the loss on those pixels (lambda falls
after a success and rises after a failure, per candidate).

On sharp pixels the basin of that loss is a few degrees wide: the residuals are texture, and texture
decorrelates quickly. So the step runs through levels of blur, coarse to fine: at a level of ``sigma``
pixels, each residual compares a pixel of the observed image blurred by a Gaussian of ``sigma`` with the
mean colour of a few rays jittered about that pixel by the same Gaussian, which is the model's image
blurred alike; the last level (``sigma`` 0) is one ray per pixel. Each level draws its own pixels in the
object's box.

The Jacobian is exact: each ray's colour derivatives with respect to its origin and direction come from
three backward passes (:func:`nerfinv_plugin.model.render.render_ray_jacobians`) and are carried to the
screw ``T = C exp([S] delta) C^-1 T0`` about the target centre ``C`` analytically: a screw (w, v) moves a
ray's origin o by ``w x (o - C) + v`` and its direction d by ``w x d``.
"""

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3
from nerfinv_plugin.inversion.optimizer import (
    IterationRecord,
    OptimizerConfig,
    PreparedFrame,
    StepResult,
    centred,
    rank,
)
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import AS_TRAINED, RayJacobians, RenderSettings, render_ray_jacobians

LAMBDA_START = 1e-2
"""Marquardt damping at the start of a level, relative to the diagonal of J^T J."""
LAMBDA_RANGE = (1e-5, 1e4)
SETTLED_AFTER = 3
"""Consecutive failed steps after which a candidate counts as settled for the level and is not rendered."""


def screw_jacobian(rays: RayJacobians, centre: Tensor) -> Tensor:
    """Colour Jacobian [N, P, 3, 6] with respect to the screw (w, v) about ``centre`` [3]:
    ``dr/dw = (o - C) x g_o + d x g_d`` (as ``g . (w x a) = w . (a x g)``) and ``dr/dv = g_o``, for each
    colour channel's gradients g with respect to the ray's origin o and direction d."""
    offset = (rays.origins - centre)[:, :, None, :].expand_as(rays.d_origin)
    direction = rays.directions[:, :, None, :].expand_as(rays.d_direction)
    d_w = torch.cross(offset, rays.d_origin, dim=-1) + torch.cross(direction, rays.d_direction, dim=-1)
    return torch.cat([d_w, rays.d_origin], -1)


@dataclass(frozen=True)
class BlurLevel:
    """One level of the coarse-to-fine schedule: ``pixels`` [P, 2] (row, col) of the observed image blurred
    by ``sigma`` px (``observed`` [P, 3]) and the sub-pixel ray positions [P * K, 2] whose mean colour
    stands for each of them (K jittered positions per pixel; one, at the pixel, when ``sigma`` is 0)."""

    sigma: float
    observed: Tensor
    rays: Tensor
    per_pixel: int

    @classmethod
    def draw(cls, frame: PreparedFrame, sigma: float, rays_per_pixel: int, rng: np.random.Generator) -> "BlurLevel":
        """A level of ``sigma`` px: fresh pixels from the frame's sampler and fresh jitter, both from ``rng``."""
        pixels = frame.sampler.sample(rng)
        image = frame.observed.cpu().numpy()
        if sigma > 0:
            image = cv2.GaussianBlur(image, (0, 0), sigma)
            offsets = rng.normal(0.0, sigma, (rays_per_pixel, 2))
            offsets -= offsets.mean(0)  # the jitter's centroid on the pixel: no shift at coarse levels
        else:
            offsets = np.zeros((1, 2))
        height, width = image.shape[:2]
        positions = pixels[:, None, :].astype(np.float64) + offsets[None]
        positions[..., 0] = positions[..., 0].clip(0.0, height - 1e-3)
        positions[..., 1] = positions[..., 1].clip(0.0, width - 1e-3)
        device = frame.observed.device
        return cls(sigma, torch.as_tensor(image[pixels[:, 0], pixels[:, 1]], device=device),
                   torch.as_tensor(positions.reshape(-1, 2), dtype=torch.float32, device=device), len(offsets))


class GaussNewtonStep:
    """N candidates over one step, an iteration (one render with Jacobians) at a time; the same interface
    as :class:`~nerfinv_plugin.inversion.optimizer.CandidateStep`. Each level takes one iteration to
    linearise at its start and ``config.gauss_newton_iterations`` trial steps after it. It prunes nothing
    (a settled candidate keeps its place in the ranking), so ``min_candidates`` changes nothing here."""

    def __init__(self, loaded: LoadedModel, start: Tensor, frame: PreparedFrame, config: OptimizerConfig,
                 min_candidates: int = 1, settings: RenderSettings = AS_TRAINED):
        device = loaded.device
        self.loaded, self.frame, self.config, self.settings = loaded, frame, config, settings
        self.current = start.to(device, torch.float32).clone()
        n = self.current.shape[0]
        self.to_centre, self.from_centre = centred(frame.centre)
        self.alive = torch.isfinite(self.current).flatten(1).all(1)
        self.active = self.alive.clone()
        self.cost = torch.full((n,), torch.inf, device=device)
        self.residuals = self.jacobian = torch.zeros(0)
        self.damping = torch.full((n,), LAMBDA_START, device=device)
        self.failures = torch.zeros(n, dtype=torch.long, device=device)
        self.levels = list(config.gauss_newton_blur_px)
        self.level: BlurLevel | None = None
        self.trials = 0
        """Trial steps taken on the current level."""
        self.history: list[IterationRecord] = []
        self.stopped = not bool(self.alive.any())

    def poses(self) -> Tensor:
        """Current candidates [N, 4, 4]."""
        return self.current

    def _linearize(self, c2w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Residuals [K, M], Jacobians [K, M, 6] and loss [K] (mean squared colour error) of the poses
        ``c2w`` [K, 4, 4] on the current level; the loss is infinite where the Jacobian is not finite."""
        level = self.level
        rays = render_ray_jacobians(self.loaded, c2w, self.frame.intrinsics, level.rays, self.settings)
        k, per_pixel = c2w.shape[0], level.per_pixel
        colours = rays.rgb.reshape(k, -1, per_pixel, 3).mean(2)
        jacobian = screw_jacobian(rays, self.frame.centre).reshape(k, -1, per_pixel, 3, 6).mean(2)
        residuals, jacobian = (colours - level.observed[None]).flatten(1), jacobian.flatten(1, 2)
        loss = (residuals**2).mean(1)
        return residuals, jacobian, torch.where(torch.isfinite(jacobian).flatten(1).all(1), loss, torch.inf)

    def _begin_level(self, rng: np.random.Generator) -> None:
        """Draw the next level's pixels and linearise every live candidate on them."""
        self.level = BlurLevel.draw(self.frame, self.levels.pop(0), self.config.gauss_newton_rays_per_pixel, rng)
        self.trials = 0
        self.active = self.alive.clone()
        self.damping.fill_(LAMBDA_START)
        self.failures.zero_()
        which = torch.nonzero(self.active).flatten()
        n, m = self.current.shape[0], self.level.observed.numel()
        self.residuals = torch.zeros(n, m, device=self.current.device)
        self.jacobian = torch.zeros(n, m, 6, device=self.current.device)
        self.cost.fill_(torch.inf)
        if len(which):
            residuals, jacobian, cost = self._linearize(self.current[which])
            self.residuals[which], self.jacobian[which], self.cost[which] = residuals, jacobian, cost
            self.alive[which] &= torch.isfinite(cost)
            self.active &= self.alive

    def _trial(self) -> None:
        """Every active candidate's damped Gauss-Newton step, kept where it lowered the loss."""
        which = torch.nonzero(self.active).flatten()
        jacobian, residuals = self.jacobian[which], self.residuals[which]
        normal = jacobian.transpose(1, 2) @ jacobian
        gradient = jacobian.transpose(1, 2) @ residuals[..., None]
        diagonal = torch.diagonal(normal, dim1=1, dim2=2)
        floor = 1e-9 * diagonal.sum(1, keepdim=True).clamp(min=1e-12)  # a direction no ray sees stays put
        damped = normal + torch.diag_embed(self.damping[which, None] * diagonal + floor)
        delta = -torch.linalg.solve(damped, gradient)[..., 0]
        trial = self.to_centre @ exp_se3(delta) @ self.from_centre @ self.current[which]
        residuals, jacobian, cost = self._linearize(trial)
        better = cost < self.cost[which]  # an infinite loss is never better
        kept = which[better]
        self.current[kept], self.cost[kept] = trial[better], cost[better]
        self.residuals[kept], self.jacobian[kept] = residuals[better], jacobian[better]
        low, high = LAMBDA_RANGE
        self.damping[which] = torch.where(better, self.damping[which] / 3, self.damping[which] * 4).clamp(low, high)
        self.failures[which] = torch.where(better, 0, self.failures[which] + 1)
        self.active &= self.failures < SETTLED_AFTER
        self.trials += 1

    def iterate(self, rng: np.random.Generator) -> IterationRecord:
        """One render: a level's linearisation, or a trial step on it."""
        if self.level is None or self.trials >= self.config.gauss_newton_iterations or not bool(self.active.any()):
            self._begin_level(rng)
        else:
            self._trial()
        losses = torch.where(self.alive, self.cost, torch.inf)
        error = None if self.frame.error_fn is None else self.frame.error_fn(self.current).cpu().numpy()
        # a copy: the poses move on in place, and each record keeps those it was measured at
        record = IterationRecord(losses.cpu().numpy(), error, self.current.cpu().numpy().copy())
        self.history.append(record)
        last_level_done = not self.levels and (self.trials >= self.config.gauss_newton_iterations
                                               or not bool(self.active.any()))
        self.stopped = last_level_done or not bool(self.alive.any())
        return record

    def result(self) -> StepResult:
        """The final poses ranked on the frame's evaluation pixels."""
        return rank(self.loaded, self.current, self.alive, self.alive.clone(), self.frame, self.config,
                    self.settings, self.history)
