"""How often the view bank proposes the right attitude: for every frame with ground truth and the object
wholly in view, whether one of the first k hypotheses is within a threshold of the true attitude, and
whether the first is; and what building and matching the bank cost."""

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import torch

from nerfinv_plugin.data.sequences import Sequence, read_sequence
from nerfinv_plugin.geometry.errors import rotation_error_deg
from nerfinv_plugin.initialization.bank import BankConfig, bank_file
from nerfinv_plugin.initialization.detect import find_object
from nerfinv_plugin.initialization.initializer import Initializer
from nerfinv_plugin.inversion.session import bound_rays
from nerfinv_plugin.inversion.settings import RenderConfig
from nerfinv_plugin.model.loaded import LoadedModel


@dataclass(frozen=True)
class Recall:
    """Recall over the usable frames of one sequence."""

    name: str
    frames: int
    """Frames scored (ground truth known, object found and not cut by the border)."""
    skipped: int
    """Frames left out: no truth, no object found, or the object touching the border."""
    top1: float
    topk: float
    median_best_deg: float
    """Median over frames of the best hypothesis' rotation error."""
    median_range_error: float
    """Median relative range error of the first hypothesis."""
    match_s: list[float]
    """Seconds to match each frame (detection, crop, scores, suppression, poses)."""


def bank_recall(loaded: LoadedModel, initializer: Initializer, sequence: Sequence, name: str, k: int,
                threshold_deg: float) -> Recall:
    """Match every usable frame of ``sequence`` against ``initializer``'s bank and score its ``k`` first
    hypotheses against the truth (rotation, and the first one's range from the target centre)."""
    hits1, hitsk, best, ranges, times, skipped = [], [], [], [], [], 0
    for frame in sequence.frames:
        tic = time.perf_counter()
        detection = find_object(frame.image)
        if frame.c2w_true is None or detection is None or detection.touches_border:
            skipped += 1
            continue
        poses = initializer.poses(frame.image, detection, sequence.intrinsics, k)
        times.append(time.perf_counter() - tic)
        truth = torch.as_tensor(loaded.dataset_to_model(frame.c2w_true), dtype=torch.float32)
        errors = rotation_error_deg(poses, truth).numpy()
        hits1.append(errors[0] < threshold_deg)
        hitsk.append(errors.min() < threshold_deg)
        best.append(float(errors.min()))
        centre = torch.as_tensor(initializer.centre, dtype=torch.float32)
        true_range = float(torch.linalg.norm(truth[:3, 3] - centre))
        ranges.append(abs(float(torch.linalg.norm(poses[0, :3, 3] - centre)) - true_range) / true_range)
    if not best:
        return Recall(name, 0, skipped, float("nan"), float("nan"), float("nan"), float("nan"), [])
    return Recall(name, len(best), skipped, float(np.mean(hits1)), float(np.mean(hitsk)), float(np.median(best)),
                  float(np.median(ranges)), times)


@dataclass(frozen=True)
class BankBenchmark:
    """The bank as ``ns-invert`` builds it, and its recall on each sequence."""

    radius_m: float | None
    """Radius (dataset metres) of the sphere rays are bounded to and the bank frames; ``None`` when rays are
    not bounded (the bank then frames the object's extent read off the model)."""
    radius_given: bool
    """The radius came from the settings, not measured on the model."""
    bound_s: float
    """Seconds bounding the rays (measuring the object's radius, unless given)."""
    built: bool
    """Rendered here (``False``: read from the cache)."""
    build_s: float
    """Seconds the renders took when the bank was built (the cache keeps it)."""
    ready_s: float
    """Seconds until the bank could match: cache look-up or renders, and its entries."""
    entries: int
    """Views x in-plane angles that hold the object."""
    recalls: list[Recall]

    @property
    def frames(self) -> int:
        return sum(r.frames for r in self.recalls)

    def overall(self) -> tuple[float, float]:
        """``(top-1, top-k)`` recall over the scored frames of all sequences (NaN when none was scored)."""
        if not self.frames:
            return float("nan"), float("nan")
        scored = [r for r in self.recalls if r.frames]
        return (sum(r.top1 * r.frames for r in scored) / self.frames,
                sum(r.topk * r.frames for r in scored) / self.frames)


def bank_benchmark(loaded: LoadedModel, sequences: Iterable[str], target: tuple[float, float, float],
                   bank: BankConfig, render: RenderConfig, hypotheses: int, threshold_deg: float,
                   resolution: tuple[int, int] | None = None, rebuild: bool = False,
                   on_build: Callable[[int], Callable[[int], None]] | None = None) -> BankBenchmark:
    """Bound rays as ``render`` says and build (or read) the bank about ``target`` (dataset frame) as
    ``ns-invert`` does, ``rebuild`` forcing the renders (to time them), then score the first ``hypotheses``
    of every usable frame of each sequence (read at ``resolution``, one at a time). ``on_build`` is the
    bank's progress callback."""
    centre = loaded.point_to_model(np.asarray(target, dtype=np.float64))
    with torch.no_grad():
        tic = time.perf_counter()
        settings, _ = bound_rays(loaded, torch.as_tensor(centre, dtype=torch.float32), render)
        bound_s = time.perf_counter() - tic
        sphere = settings.target_sphere
        if rebuild and sphere is not None:
            bank_file(loaded, settings, centre, float(sphere[1]), bank).unlink(missing_ok=True)
        tic = time.perf_counter()
        initializer = Initializer.create(loaded, settings, centre, bank, on_build)
        ready_s = time.perf_counter() - tic
        recalls = [bank_recall(loaded, initializer, read_sequence(spec, resolution=resolution), spec, hypotheses,
                               threshold_deg) for spec in sequences]
    return BankBenchmark(None if sphere is None else float(sphere[1]) / loaded.dataparser_scale,
                         render.target_radius_m is not None, bound_s, initializer.built, initializer.build_s, ready_s,
                         len(initializer.entries.views), recalls)
