"""A Kalman filter on SE(3) for the camera's pose relative to the target: where the next frame's candidates
start (``--monte-carlo.motion filter``).

Why not constant velocity: predicting with the last frame-to-frame motion of the estimates adds the
difference of two noisy estimates to a noisy estimate, so the prediction's error is about twice the
estimates' own (docs/benchmarks.md: median 10.6 degrees against 1.4 without a prior). A filter weighs
each frame's estimate against what the motion so far predicts, so its prediction is never noisier than
the estimates, and it can refuse an estimate that its own uncertainty says is implausible.

The state is the pose ``X`` of the camera in the *target frame* (the model frame moved so that the target
centre is its origin: ``X = C^-1 c2w`` with ``C`` the translation to the centre) and a twist ``xi = [w, v]``
per frame (angular part first, as in :mod:`nerfinv_plugin.geometry.se3`), acting on the left:

    X_{k+1} = exp(xi_k) X_k,        xi_{k+1} = xi_k + a_k,        a_k ~ N(0, diag(s_w^2 I, s_v^2 I))

so a camera circling the target at a steady rate has a constant twist with ``v = 0``. The uncertainty is
kept on a left error ``X = exp(d) X_hat`` (error-state filter), 12 numbers ``e = [d, d_xi]``:

    F = [[Ad(exp(xi)), J(xi)], [0, I]],      Q = [[Qa / 4, Qa / 2], [Qa / 2, Qa]]   (one frame, piecewise
                                                                                     constant acceleration)
    P- = F P F^T + Q

(over ``n`` frames: ``n xi``, and ``Q`` of the same model over ``n``; the tracker predicts at the start of a
frame, over however many frames went by since the last one it estimated);

with ``Ad`` the adjoint of SE(3) and ``J`` its left Jacobian. A measurement is a pose ``Z`` with a
covariance ``R`` (of a left error in the same frame); the innovation is ``y = log(Z X-^-1)``, ``H = [I 0]``,
``S = P-_dd + R``. The measurement is **rejected** when its Mahalanobis distance ``y^T S^-1 y`` exceeds
the chi-square quantile of 6 degrees of freedom at ``gate_probability``: the filter stays on its
prediction. After ``max_rejections`` rejections in a row the filter restarts from the measurement (the
motion changed, or the filter lost the target). Otherwise ``K = P- H^T S^-1``, ``e = K y``,
``X = exp(e_d) X-``, ``xi = xi- + e_xi`` and ``P = (I - K H) P- (I - K H)^T + K R K^T`` (Joseph form).

The measurement covariance comes from the fit (:func:`fit_covariance`): a floor (the optimizer's typical
per-frame error, settings in degrees and metres) plus the loss-weighted spread of the candidates a step
keeps about its best.
"""

import math
from dataclasses import dataclass, replace
from typing import Literal

import torch
from scipy.stats import chi2
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3, hat, log_se3

Verdict = Literal["started", "accepted", "rejected", "restarted"]


@dataclass
class MotionFilterConfig:
    """The SE(3) motion filter (``--monte-carlo.motion filter``): its noise, in dataset degrees and metres per
    frame, and its gate."""

    measurement_deg: float = 2.0
    """Least standard deviation of a frame's estimate, each rotation axis (about the target): the optimizer's
    typical per-frame error (1-4 degrees on our models, docs/benchmarks.md). The spread of the kept
    candidates adds to it."""
    measurement_m: float = 0.1
    """Least standard deviation of a frame's estimate, each translation axis (metres; 2-6% of a 5 m range
    measured)."""
    accel_deg: float = 1.0
    """Process noise: standard deviation of the change of the angular rate from one frame to the next, each
    axis (degrees per frame per frame). Larger follows a changing tumble sooner and smooths less."""
    accel_m: float = 0.02
    """Process noise: standard deviation of the change of the linear rate per frame, each axis (metres per
    frame per frame)."""
    initial_rate_deg: float = 10.0
    """Standard deviation of the unknown angular rate when the filter starts (degrees per frame)."""
    initial_speed_m: float = 0.5
    """Standard deviation of the unknown linear rate when the filter starts (metres per frame)."""
    gate_probability: float = 0.997
    """A frame's estimate whose Mahalanobis distance from the prediction is beyond this chi-square quantile
    (6 degrees of freedom: 20.1 at 0.997) is rejected as an outlier and the filter stays on its
    prediction."""
    max_rejections: int = 3
    """After this many rejected frames in a row, the next rejected one restarts the filter from its
    estimate (the motion changed, or the filter lost the target). At least 1."""


@dataclass(frozen=True)
class PoseMeasurement:
    """One frame's estimate as the filter reads it (target frame, model units)."""

    pose: Tensor
    """[4, 4] float64 camera pose in the target frame."""
    covariance: Tensor
    """[6, 6] float64 covariance of its left error ``[d_w (rad), d_v (model units)]``."""


@dataclass(frozen=True)
class MotionState:
    """The filter's estimate after a prediction or an update (target frame, model units)."""

    pose: Tensor
    """[4, 4] float64 camera pose in the target frame."""
    twist: Tensor
    """[6] float64 motion per frame ``[w, v]``, on the left."""
    covariance: Tensor
    """[12, 12] float64 covariance of the error ``[d (6), d_twist (6)]``."""
    rejections: int = 0
    """Measurements rejected in a row just before this state."""

    def to_dict(self) -> dict:
        return {"pose": self.pose, "twist": self.twist, "covariance": self.covariance,
                "rejections": self.rejections}

    @classmethod
    def from_dict(cls, data: dict) -> "MotionState":
        return cls(data["pose"], data["twist"], data["covariance"], data["rejections"])


def adjoint(transform: Tensor) -> Tensor:
    """[6, 6] adjoint of a rigid transform [4, 4] for twists ``[w, v]``: ``Ad(T) xi`` is ``T xi^ T^-1``."""
    rot, p = transform[:3, :3], transform[:3, 3]
    out = torch.zeros(6, 6, dtype=transform.dtype)
    out[:3, :3] = rot
    out[3:, 3:] = rot
    out[3:, :3] = hat(p) @ rot
    return out


def left_jacobian(xi: Tensor, terms: int = 12) -> Tensor:
    """[6, 6] left Jacobian of SE(3) at ``xi`` [6]: ``exp(xi + e) = exp(J e) exp(xi)`` to first order in
    ``e``. Its series ``sum ad^n / (n + 1)!``, exact to double precision for the few degrees a frame turns
    (each term is smaller by ``|xi| / n``)."""
    ad = torch.zeros(6, 6, dtype=xi.dtype)
    ad[:3, :3] = hat(xi[:3])
    ad[3:, 3:] = hat(xi[:3])
    ad[3:, :3] = hat(xi[3:])
    out, term = torch.eye(6, dtype=xi.dtype), torch.eye(6, dtype=xi.dtype)
    for n in range(1, terms):
        term = term @ ad / (n + 1)
        out = out + term
    return out


class MotionFilter:
    """The filter of this module's docstring, its noise in model units (``scale``: model units per metre)."""

    def __init__(self, config: MotionFilterConfig, scale: float = 1.0):
        self.config = config
        rad, unit = math.radians(1.0), scale
        self.floor = _diag(config.measurement_deg * rad, config.measurement_m * unit)
        self.accel = _diag(config.accel_deg * rad, config.accel_m * unit)
        self.initial_rate = _diag(config.initial_rate_deg * rad, config.initial_speed_m * unit)
        self.gate = float(chi2.ppf(config.gate_probability, 6))

    def start(self, measurement: PoseMeasurement) -> MotionState:
        """The filter on its first measurement: that pose, no motion yet (with a wide uncertainty)."""
        covariance = torch.zeros(12, 12, dtype=torch.float64)
        covariance[:6, :6] = measurement.covariance
        covariance[6:, 6:] = self.initial_rate
        return MotionState(measurement.pose.double(), torch.zeros(6, dtype=torch.float64), covariance)

    def predict(self, state: MotionState, frames: int = 1) -> MotionState:
        """The state ``frames`` frames later (a frame skipped when the clock or a missing object says so):
        ``X- = exp(n xi) X``, ``P- = F P F^T + Q`` with ``F = [[Ad(exp(n xi)), n J(n xi)], [0, I]]`` and the
        piecewise-constant acceleration noise ``Q = [[n^4 Qa / 4, n^3 Qa / 2], [n^3 Qa / 2, n^2 Qa]]``."""
        n = float(frames)
        motion = exp_se3(n * state.twist)
        f = torch.eye(12, dtype=torch.float64)
        f[:6, :6] = adjoint(motion)
        f[:6, 6:] = n * left_jacobian(n * state.twist)
        a = self.accel
        q = torch.cat([torch.cat([n**4 * a / 4, n**3 * a / 2], 1), torch.cat([n**3 * a / 2, n**2 * a], 1)])
        covariance = f @ state.covariance @ f.T + q
        return replace(state, pose=motion @ state.pose, covariance=(covariance + covariance.T) / 2)

    def update(self, predicted: MotionState | None, measurement: PoseMeasurement) -> tuple[MotionState, Verdict]:
        """The state after ``measurement``, from the prediction for its frame (None: the first frame)."""
        if predicted is None:
            return self.start(measurement), "started"
        y = log_se3(measurement.pose.double() @ torch.linalg.inv(predicted.pose))  # innovation
        p = predicted.covariance
        s = p[:6, :6] + measurement.covariance
        if float(y @ torch.linalg.solve(s, y)) > self.gate:  # squared Mahalanobis distance
            if predicted.rejections >= self.config.max_rejections:
                return self.start(measurement), "restarted"
            return replace(predicted, rejections=predicted.rejections + 1), "rejected"
        gain = torch.linalg.solve(s, p[:6, :]).T  # P H^T S^-1, S symmetric
        correction = gain @ y
        i_kh = torch.eye(12, dtype=torch.float64)
        i_kh[:, :6] -= gain
        covariance = i_kh @ p @ i_kh.T + gain @ measurement.covariance @ gain.T
        return MotionState(exp_se3(correction[:6]) @ predicted.pose, predicted.twist + correction[6:],
                           (covariance + covariance.T) / 2), "accepted"

    def fit_covariance(self, best: Tensor, kept: Tensor, losses: Tensor) -> Tensor:
        """The covariance [6, 6] of a frame's estimate ``best`` [4, 4] (target frame) from the fit: the floor
        plus the spread about it of the candidates the step kept, ``kept`` [K, 4, 4] with their ranking
        ``losses`` [K], each weighted by ``best loss / its loss``. Candidates that the loss can hardly tell
        from the best (a flat direction, a near-symmetric look-alike) make the estimate less certain along
        where they lie; candidates at the best, or far worse than it, add nothing."""
        deviations = log_se3(kept.double() @ torch.linalg.inv(best.double()))
        losses = losses.double()
        weights = torch.where(torch.isfinite(losses), losses.min().clamp_min(1e-12) / losses.clamp_min(1e-12), 0.0)
        spread = (weights[:, None, None] * deviations[:, :, None] * deviations[:, None, :]).sum(0)
        return self.floor + spread / weights.sum().clamp_min(1.0)


def _diag(angular: float, linear: float) -> Tensor:
    """[6, 6] diagonal covariance of standard deviations ``angular`` (3 axes) then ``linear`` (3 axes)."""
    return torch.diag(torch.tensor([angular] * 3 + [linear] * 3, dtype=torch.float64) ** 2)
