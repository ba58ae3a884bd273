"""How a grid scores its runs, the way the thesis counts them (chapter 5: "converges to an angular error of
less than 10 degrees 22 times over 30 experiments").

A run succeeds under a threshold when the rotation error of its LAST frame is below it: a tracker has to
end on the target, and passing close to it on the way does not count. The best and mean errors over the
frames are kept beside it, to tell a run that never came close from one that lost the target.
"""

import numpy as np

from nerfinv_plugin.results.records import FrameResult

SUCCESS_DEG = (2.0, 3.0, 5.0, 10.0)
"""Thresholds on the last frame's rotation error: the thesis reports 3, 5 and 10 degrees; 2 is the
tightest threshold of ``ns-invert``'s own summary."""
FIRST_UNDER_DEG = 5.0
"""Threshold of the time-to-target column: how soon the tracker is on the target, not only whether."""
ALL_CASES = "all cases"
"""The case label of a variant's totals over every case."""


class ScoringError(Exception):
    """A run whose results cannot be scored as a grid scores them."""


def under_key(threshold_deg: float) -> str:
    """Key of a cell's success flag (and of a group's success count) under ``threshold_deg``."""
    return f"under_{threshold_deg:g}deg"


def cell_metrics(rows: list[FrameResult]) -> dict:
    """The numbers a grid keeps of one run, from its per-frame rows (``results.jsonl``)."""
    if not rows:
        raise ScoringError("the run finished no frame")
    if any(row.rotation_deg is None for row in rows):
        raise ScoringError("the sequence has frames without a true pose, and a grid scores runs against it")
    rotation = np.array([row.rotation_deg for row in rows], dtype=float)
    wall = np.array([row.wall_time_s for row in rows], dtype=float)
    first = next((row.elapsed_s for row in rows if row.rotation_deg < FIRST_UNDER_DEG), None)
    return {"frames": len(rows), "final_rotation_deg": float(rotation[-1]), "min_rotation_deg": float(rotation.min()),
            "mean_rotation_deg": float(rotation.mean()), "final_translation_m": float(rows[-1].translation_m),
            "final_translation_rel": float(rows[-1].translation_rel), "wall_time_s": float(wall.sum()),
            "time_per_frame_s": float(wall.mean()), "time_to_5deg_s": None if first is None else float(first),
            **{under_key(t): bool(rotation[-1] < t) for t in SUCCESS_DEG}}


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def group_summary(variant: str, case: str, cells: list[dict]) -> dict:
    """Successes k of n finished runs under each threshold, with the typical error and cost. Failed and
    unfinished cells are counted apart, never as failures of the method: they say nothing about it."""
    done = [c for c in cells if c["status"] == "done"]
    return {"variant": variant, "case": case, "cells": len(cells), "done": len(done),
            "failed": sum(c["status"] == "failed" for c in cells),
            "successes": {under_key(t): sum(c[under_key(t)] for c in done) for t in SUCCESS_DEG},
            "median_final_rotation_deg": _median([c["final_rotation_deg"] for c in done]),
            "median_final_translation_m": _median([c["final_translation_m"] for c in done]),
            "mean_time_per_frame_s": _mean([c["time_per_frame_s"] for c in done]),
            "mean_wall_time_s": _mean([c["wall_time_s"] for c in done])}


def aggregate(records: list[dict], by_case: bool) -> list[dict]:
    """One summary per (variant, case), or per variant over all cases, in the order the cells come."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for record in records:
        groups.setdefault((record["variant"], record["case"] if by_case else ALL_CASES), []).append(record)
    return [group_summary(variant, case, cells) for (variant, case), cells in groups.items()]
