"""Numbers that sum up a run's per-frame results."""

import numpy as np

SUCCESS_DEG = (2.0, 5.0, 10.0)
"""Rotation-error thresholds for success rates (the thesis counts runs under 3, 5 and 10 degrees)."""
SUCCESS_REL = (0.01, 0.05, 0.1)
"""Translation-error thresholds, relative to the range (SPEC2021's e_t)."""


def summarize(rows: list[dict]) -> dict:
    """Errors, success rates and timing over the frames done. Success rates count frames whose error is
    under each threshold, out of the frames that have ground truth."""
    summary: dict = {"frames_done": len(rows)}
    if not rows:
        return summary
    wall = np.array([r["wall_time_s"] for r in rows])
    summary |= {"wall_time_s": float(wall.sum()), "mean_time_per_frame_s": float(wall.mean()),
                "final_loss": rows[-1]["loss"]}
    truth = [r for r in rows if r.get("rotation_deg") is not None]
    if not truth:
        return summary
    rot = np.array([r["rotation_deg"] for r in truth])
    rel = np.array([r["translation_rel"] for r in truth])
    summary |= {
        "frames_with_truth": len(truth),
        "rotation_deg": {"mean": float(rot.mean()), "median": float(np.median(rot)), "max": float(rot.max()),
                         "final": float(rot[-1])},
        "translation_m": {"mean": float(np.mean([r["translation_m"] for r in truth])),
                          "final": float(truth[-1]["translation_m"])},
        "translation_rel": {"mean": float(rel.mean()), "median": float(np.median(rel))},
        "score": {"mean": float(np.mean([r["score"] for r in truth]))},
        "success_rotation": {f"{t:g}deg": float(np.mean(rot < t)) for t in SUCCESS_DEG},
        "success_translation": {f"{t:g}": float(np.mean(rel < t)) for t in SUCCESS_REL},
    }
    return summary
