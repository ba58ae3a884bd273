"""The files of a run folder, written so that an interruption at any moment loses nothing already computed.

``state.pt`` holds everything (per-frame rows, per-step rows, the tracker's state and the elapsed time)
and is replaced atomically after every step; ``results.jsonl``, ``results.csv`` and ``steps.jsonl`` are
regenerated from it right after, also atomically. A resumed run reads ``state.pt`` and goes on; if it
was interrupted between the two writes, the regenerated files catch up at once.
"""

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import torch

from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.results.records import FrameResult, RunSummary, StepRow

CONFIG = "config.yml"
STATE = "state.pt"
RESULTS_JSONL = "results.jsonl"
RESULTS_CSV = "results.csv"
STEPS_JSONL = "steps.jsonl"
SUMMARY = "summary.json"

CSV_COLUMNS = ("frame", "name", "steps", "wall_time_s", "elapsed_s", "loss", "outline_loss", "silhouette_weight",
               "rotation_deg", "translation_m", "translation_rel", "score", "candidates", "dropped", "object_found",
               "reinitialized", "bank_added", "interpolated", "observed_s", "estimated_s", "latency_s", "qw", "qx",
               "qy", "qz", "rx", "ry", "rz")
"""One row per frame; the model-frame pose is in the JSONL only (a 4x4 matrix does not fit a column)."""


def _csv(rows: list[FrameResult]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for row in rows:
        flat = {**row.to_json(), **dict(zip(("qw", "qx", "qy", "qz"), row.q)),
                **dict(zip(("rx", "ry", "rz"), row.r))}
        writer.writerow(["" if flat.get(c) is None else flat[c] for c in CSV_COLUMNS])
    return out.getvalue()


def _jsonl(records: list[FrameResult] | list[StepRow]) -> str:
    return "".join(json.dumps(r.to_json()) + "\n" for r in records)


def _read_jsonl(path: Path) -> list[dict]:
    text = path.read_text() if path.is_file() else ""
    return [json.loads(line) for line in text.splitlines() if line]


@dataclass
class SavedRun:
    """What :meth:`RunFolder.save` stored last: everything a resumed run continues from."""

    rows: list[FrameResult]
    steps: list[StepRow]
    tracker: dict
    """:meth:`TrackerState.state_dict` of the tracker after the last step."""
    elapsed_s: float


class RunFolder:
    """Reads and writes the results of one run in ``path``."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def save(self, rows: list[FrameResult], steps: list[StepRow], tracker: dict, elapsed_s: float) -> None:
        buffer = io.BytesIO()
        torch.save({"rows": [r.to_json() for r in rows], "steps": [s.to_json() for s in steps], "tracker": tracker,
                    "elapsed_s": elapsed_s}, buffer)
        write_atomic(self.path / STATE, buffer.getvalue())
        self.export(rows, steps)

    def export(self, rows: list[FrameResult], steps: list[StepRow]) -> None:
        write_atomic(self.path / RESULTS_JSONL, _jsonl(rows))
        write_atomic(self.path / RESULTS_CSV, _csv(rows))
        write_atomic(self.path / STEPS_JSONL, _jsonl(steps))

    def load(self) -> SavedRun | None:
        """What :meth:`save` stored last, or ``None`` for a run that has not finished a step."""
        if not (self.path / STATE).is_file():
            return None
        saved = torch.load(self.path / STATE, weights_only=False)
        return SavedRun([FrameResult.from_json(r) for r in saved["rows"]],
                        [StepRow.from_json(s) for s in saved["steps"]], saved["tracker"], saved["elapsed_s"])

    def rows(self) -> list[FrameResult]:
        """The per-frame results as written (for reports and tests)."""
        return [FrameResult.from_json(r) for r in _read_jsonl(self.path / RESULTS_JSONL)]

    def steps(self) -> list[StepRow]:
        """The per-step rows as written."""
        return [StepRow.from_json(s) for s in _read_jsonl(self.path / STEPS_JSONL)]

    def summary(self) -> RunSummary | None:
        """``summary.json``, or ``None`` while it is not written (a run going on or interrupted) or cut short."""
        try:
            return RunSummary.from_json(json.loads((self.path / SUMMARY).read_text()))
        except (OSError, ValueError, TypeError):
            return None

    def write_summary(self, summary: RunSummary) -> None:
        write_atomic(self.path / SUMMARY, json.dumps(summary.to_json(), indent=2))
