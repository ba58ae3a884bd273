"""How often the view bank proposes the right attitude: for every frame with ground truth and the object
wholly in view, whether one of the first k hypotheses is within a threshold of the true attitude, and
whether the first is."""

import time
from dataclasses import dataclass

import numpy as np
import torch

from nerfinv_plugin.data.sequences import Sequence
from nerfinv_plugin.geometry.se3 import geodesic_deg
from nerfinv_plugin.initialization.detect import find_object
from nerfinv_plugin.initialization.initializer import Initializer
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
        errors = geodesic_deg(poses[:, :3, :3], truth[None, :3, :3].expand(len(poses), 3, 3)).numpy()
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
