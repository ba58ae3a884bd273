"""Numbers that sum up a run's per-frame results."""

import numpy as np

from nerfinv_plugin.results.records import Accuracy, ErrorStatistics, FrameResult, RunSummary

SUCCESS_DEG = (2.0, 5.0, 10.0)
"""Rotation-error thresholds for success rates (the thesis counts runs under 3, 5 and 10 degrees)."""
SUCCESS_REL = (0.01, 0.05, 0.1)
"""Translation-error thresholds, relative to the range (SPEC2021's e_t)."""
LOCK_DEG = 5.0
"""A frame estimated under this rotation error is locked: the time to first lock is when the first one was."""


def rotation_key(threshold_deg: float) -> str:
    """Key of a rotation success rate in ``RunSummary.success_rotation``, shared by every reader."""
    return f"{threshold_deg:g}deg"


def translation_key(threshold_rel: float) -> str:
    """Key of a translation success rate in ``RunSummary.success_translation``."""
    return f"{threshold_rel:g}"


def statistics(values: np.ndarray) -> ErrorStatistics:
    """The same four numbers for every error: the typical one, the worst, and where the run ended."""
    return ErrorStatistics(mean=float(values.mean()), median=float(np.median(values)), max=float(values.max()),
                           final=float(values[-1]))


def accuracy(rows: list[FrameResult]) -> Accuracy | None:
    """Errors and success rates over the rows with ground truth; ``None`` when none has it."""
    truth = [r for r in rows if r.rotation_deg is not None]
    if not truth:
        return None
    rot = np.array([r.rotation_deg for r in truth])
    rel = np.array([r.translation_rel for r in truth])
    return Accuracy(
        frames=len(truth), rotation_deg=statistics(rot),
        translation_m=statistics(np.array([r.translation_m for r in truth])),
        translation_rel=statistics(rel), score=statistics(np.array([r.score for r in truth])),
        success_rotation={rotation_key(t): float(np.mean(rot < t)) for t in SUCCESS_DEG},
        success_translation={translation_key(t): float(np.mean(rel < t)) for t in SUCCESS_REL})


def timing(rows: list[FrameResult]) -> dict:
    """Compute time, the clock, latency and the first lock, over the rows done (the estimated ones: an
    interpolated frame cost nothing and no step looked at it)."""
    estimated = [r for r in rows if not r.interpolated]
    wall = np.array([r.wall_time_s for r in estimated])
    latency = np.array([r.latency_s for r in estimated if r.latency_s is not None])
    locked = next((r for r in estimated if r.rotation_deg is not None and r.rotation_deg < LOCK_DEG), None)
    return {"wall_time_s": float(wall.sum()), "mean_time_per_frame_s": float(wall.mean()),
            "final_loss": estimated[-1].loss, "frames_estimated": len(estimated),
            "frames_skipped": len(rows) - len(estimated), "clock_end_s": estimated[-1].estimated_s,
            "latency_s": statistics(latency) if latency.size else None,
            "time_to_first_lock_s": None if locked is None else locked.estimated_s,
            "first_lock_frame": None if locked is None else locked.frame}


def summarize(rows: list[FrameResult]) -> RunSummary:
    """Errors, success rates, timing and latency over the frames done. Success rates count frames whose error
    is under each threshold, out of the frames that have ground truth; frames without it count only for time
    and loss, so a partly labelled sequence is scored on its labelled frames alone. The errors count every
    frame, interpolated ones included; ``estimated_only`` has them over the estimated frames alone."""
    if not rows:
        return RunSummary(frames_done=0)
    times = timing(rows)
    every = accuracy(rows)
    if every is None:
        return RunSummary(frames_done=len(rows), **times)
    skipped = any(r.interpolated for r in rows)
    return RunSummary(
        frames_done=len(rows), **times,
        frames_with_truth=every.frames, rotation_deg=every.rotation_deg, translation_m=every.translation_m,
        translation_rel=every.translation_rel, score=every.score, success_rotation=every.success_rotation,
        success_translation=every.success_translation,
        estimated_only=accuracy([r for r in rows if not r.interpolated]) if skipped else None,
    )
