"""The run's clock: which frame each Monte Carlo step looks at, and when its estimate is ready.

Every frame has an observation time (seconds after the first frame: SHIRT's 5 s spacing, or
``--frame-interval-s``). The clock holds the simulated time of the solver: it starts when the first frame is
observed and advances by every piece of compute charged to it (the bank, matching, re-initialisation,
optimisation), divided by ``--clock-speed``. Two modes:

- ``frames`` (the default, the counts of docs/benchmarks.md): the frames are taken one after the other,
  each when it has been observed and the previous one is done, however long that takes; the solver may fall
  behind the camera, and its latency then grows from frame to frame.
- ``realtime`` (the thesis' chapter 1: the target image is "the one observed after the time needed to
  perform the computation"): the camera does not wait. After a frame's steps, the next step takes the
  newest frame observed by then, skipping the ones in between; when no new frame has arrived yet, the
  solver waits for the next one rather than spend another step on the old one.

The first step always takes the first frame (its starting poses are found on it). The frames skipped get
poses interpolated on SE(3) between their neighbours' estimates (:func:`interpolated_pose`).

With ``--clock-cost-s`` an optimizer iteration costs that fixed time and nothing else is charged, so the
schedule depends on the settings alone: the same on every machine and after ``--resume``. With measured
compute time (the default) a resumed run continues from the time recorded in ``steps.jsonl``, but the
steps after it are timed on the machine as it is then, so its schedule can differ from an uninterrupted
run's.
"""

import bisect
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from nerfinv_plugin.geometry.se3 import exp_se3, log_se3

ClockMode = Literal["frames", "realtime"]


@dataclass
class Clock:
    """Simulated time of one run and the frame order it implies (see the module docstring)."""

    mode: ClockMode
    frames: int
    """Frames of the run."""
    observed_s: Sequence[float] | None
    """When each frame is observed, seconds after the first (non-decreasing); ``None``: not known (frames
    mode only: the frames are then taken as soon as the previous one is done)."""
    speed: float = 1.0
    """Simulated seconds per second of compute are ``1 / speed``: 0.1 simulates a computer ten times slower."""
    cost_s: float | None = None
    """A fixed cost per optimizer iteration instead of the compute time measured."""
    now_s: float = 0.0
    """Simulated time now, seconds after the first frame was observed."""

    def __post_init__(self) -> None:
        if self.mode == "realtime" and self.observed_s is None:
            raise ValueError("a realtime clock needs the frames' observation times")
        if self.observed_s is not None and len(self.observed_s) != self.frames:
            raise ValueError(f"{len(self.observed_s)} observation times for {self.frames} frames")

    def observed(self, k: int) -> float | None:
        """When frame ``k`` is observed (``None``: not known)."""
        return None if self.observed_s is None else float(self.observed_s[k])

    def charge(self, compute_s: float, iterations: int = 0) -> float:
        """Advance by ``compute_s`` of compute that ran ``iterations`` optimizer iterations (or by
        ``iterations * cost_s`` with a fixed cost); return the simulated seconds charged."""
        charged = (compute_s if self.cost_s is None else self.cost_s * iterations) / self.speed
        self.now_s += charged
        return charged

    def newest(self) -> int:
        """The newest frame observed by now (frame 0 is observed at time 0)."""
        assert self.observed_s is not None
        return max(0, bisect.bisect_right(self.observed_s, self.now_s + 1e-9) - 1)

    def next_frame(self, previous: int | None) -> int | None:
        """The frame the steps after frame ``previous``'s take (``None`` before the first step), waiting for
        it (advancing :attr:`now_s` to its observation) when it has not been observed yet; ``None`` once the
        sequence is done."""
        if previous is None:
            k = 0
        elif self.mode == "frames":
            k = previous + 1
        else:
            k = max(previous + 1, self.newest())
        if k >= self.frames:
            return None
        observed = self.observed(k)
        if observed is not None:
            self.now_s = max(self.now_s, observed)
        return k

    def visits(self, visited: Sequence[int] = ()) -> Iterator[int]:
        """The frames the run takes, in order: first ``visited`` (the frames a resumed run already took, as
        recorded), then each next one decided when it is asked for, that is after the steps before it were
        charged."""
        yield from visited
        k = self.next_frame(visited[-1] if visited else None)
        while k is not None:
            yield k
            k = self.next_frame(k)


def interpolated_pose(before: Tensor, after: Tensor, fraction: float) -> Tensor:
    """The pose [4, 4] a ``fraction`` (0 to 1) of the way from ``before`` to ``after`` [4, 4] along the SE(3)
    geodesic: ``before @ exp(fraction * log(before^-1 @ after))``, the rotation turning at a constant rate
    about one axis while the centre moves along a screw. The same curve for camera-to-world and
    world-to-camera poses, and unchanged by a change of world frame or of scale (the model frame and the
    dataset frame give the same poses)."""
    a, b = before.double(), after.double()
    motion = log_se3(torch.linalg.inv(a) @ b)
    return a @ exp_se3(fraction * motion)


def fraction_between(t_before: float, t: float, t_after: float) -> float:
    """Where ``t`` lies between two times, 0 at ``t_before`` and 1 at ``t_after``."""
    return (t - t_before) / (t_after - t_before)
