"""Screw motions about the target centre against the thesis' plain form, from the same starts.

nerfstudio's auto-centred model frame puts the origin at the mean camera position, and a Blender-frame
model at the dataset origin; neither need be where the target is. ``exp([S] theta) T0`` then couples
rotation and translation through the distance to that origin. This optimizes the same starts on the
same frame with both parameterisations, one Monte Carlo step each, in one process.
"""

import statistics
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal, get_args

from nerfinv_plugin.bench.observed import ObservedFrame
from nerfinv_plugin.geometry.errors import rotation_error_deg
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.tracker import Frame, MonteCarloConfig, Tracker
from nerfinv_plugin.model.loaded import LoadedModel

ScrewOrigin = Literal["target", "world"]


@dataclass(frozen=True)
class ScrewRun:
    """One parameterisation's step from one seed's starts."""

    origin: ScrewOrigin
    seed: int
    start_deg: float
    """Median rotation error of the starts (the same for both origins of a seed)."""
    best_deg: float
    """Rotation error of the step's estimate (its best-loss candidate)."""
    median_deg: float
    """Median rotation error of all candidates after the step."""
    seconds: float


@dataclass(frozen=True)
class ScrewSummary:
    """One origin's runs, as medians over the seeds."""

    origin: ScrewOrigin
    best_deg: float
    median_deg: float
    seconds: float


def screw_runs(loaded: LoadedModel, observed: ObservedFrame, candidates: int, iterations: int, min_deg: float,
               max_deg: float, shift_fraction: float, seeds: Iterable[int]) -> list[ScrewRun]:
    """For each seed, starts turned ``min_deg``-``max_deg`` about the target and moved by ``shift_fraction``
    of the true range, optimized once about the target and once about the model frame's origin."""
    frame = Frame(observed.image, observed.intrinsics, observed.name, observed.truth)
    shift = shift_fraction * observed.range_m * loaded.dataparser_scale
    truth = observed.truth
    runs = []
    for seed in seeds:
        start = observed.starts(candidates, min_deg, max_deg, shift, seed)
        start_deg = float(rotation_error_deg(start, truth).median())
        for origin in get_args(ScrewOrigin):
            tracker = Tracker(loaded, observed.centre, OptimizerConfig(iterations=iterations, screw_origin=origin),
                              MonteCarloConfig(), seed=seed)
            began = time.perf_counter()
            record = tracker.run([frame], start)[0]
            seconds = time.perf_counter() - began
            runs.append(ScrewRun(origin, seed, start_deg, float(rotation_error_deg(record.estimate, truth)),
                                 float(rotation_error_deg(record.result.c2w, truth).median()), seconds))
    return runs


def summarize(runs: list[ScrewRun]) -> list[ScrewSummary]:
    """Medians over the seeds, one row per origin present, target first."""
    out = []
    for origin in get_args(ScrewOrigin):
        mine = [r for r in runs if r.origin == origin]
        if mine:
            out.append(ScrewSummary(origin, statistics.median(r.best_deg for r in mine),
                                    statistics.median(r.median_deg for r in mine),
                                    statistics.median(r.seconds for r in mine)))
    return out
