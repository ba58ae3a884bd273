"""Numbers that sum up a run's per-frame results."""

import numpy as np

from nerfinv_plugin.results.records import ErrorStatistics, FrameResult, RunSummary

SUCCESS_DEG = (2.0, 5.0, 10.0)
"""Rotation-error thresholds for success rates (the thesis counts runs under 3, 5 and 10 degrees)."""
SUCCESS_REL = (0.01, 0.05, 0.1)
"""Translation-error thresholds, relative to the range (SPEC2021's e_t)."""


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


def summarize(rows: list[FrameResult]) -> RunSummary:
    """Errors, success rates and timing over the frames done. Success rates count frames whose error is
    under each threshold, out of the frames that have ground truth; frames without it count only for time
    and loss, so a partly labelled sequence is scored on its labelled frames alone."""
    if not rows:
        return RunSummary(frames_done=0)
    wall = np.array([r.wall_time_s for r in rows])
    timing = {"wall_time_s": float(wall.sum()), "mean_time_per_frame_s": float(wall.mean()),
              "final_loss": rows[-1].loss}
    truth = [r for r in rows if r.rotation_deg is not None]
    if not truth:
        return RunSummary(frames_done=len(rows), **timing)
    rot = np.array([r.rotation_deg for r in truth])
    rel = np.array([r.translation_rel for r in truth])
    return RunSummary(
        frames_done=len(rows), **timing,
        frames_with_truth=len(truth),
        rotation_deg=statistics(rot),
        translation_m=statistics(np.array([r.translation_m for r in truth])),
        translation_rel=statistics(rel),
        score=statistics(np.array([r.score for r in truth])),
        success_rotation={rotation_key(t): float(np.mean(rot < t)) for t in SUCCESS_DEG},
        success_translation={translation_key(t): float(np.mean(rel < t)) for t in SUCCESS_REL},
    )
