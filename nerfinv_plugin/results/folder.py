"""The files of a run folder, written so that an interruption at any moment loses nothing already computed.

``state.pt`` holds everything (per-frame rows, per-step histories, the tracker's state and the elapsed
time) and is replaced atomically after every step; ``results.jsonl``, ``results.csv`` and ``steps.jsonl``
are regenerated from it right after, also atomically. A resumed run reads ``state.pt`` and goes on; if it
was interrupted between the two writes, the regenerated files catch up at once.
"""

import csv
import io
import json
import os
from pathlib import Path

import torch

CONFIG = "config.yml"
STATE = "state.pt"
RESULTS_JSONL = "results.jsonl"
RESULTS_CSV = "results.csv"
STEPS_JSONL = "steps.jsonl"
SUMMARY = "summary.json"

CSV_COLUMNS = ("frame", "name", "steps", "wall_time_s", "elapsed_s", "loss", "rotation_deg", "translation_m",
               "translation_rel", "score", "candidates", "dropped", "object_found", "reinitialized", "bank_added",
               "qw", "qx", "qy", "qz", "rx", "ry", "rz")
"""One row per frame; the model-frame pose is in the JSONL only (a 4x4 matrix does not fit a column)."""


def write_atomic(path: Path, text: str | bytes) -> None:
    """Write through a temporary file and a rename: readers see the old file or the new one, never half."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(text.encode() if isinstance(text, str) else text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _csv(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for row in rows:
        flat = {**row, **dict(zip(("qw", "qx", "qy", "qz"), row["q"])), **dict(zip(("rx", "ry", "rz"), row["r"]))}
        writer.writerow(["" if flat.get(c) is None else flat[c] for c in CSV_COLUMNS])
    return out.getvalue()


def _jsonl(records: list[dict]) -> str:
    return "".join(json.dumps(r) + "\n" for r in records)


class RunFolder:
    """Reads and writes the results of one run in ``path``."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def save(self, rows: list[dict], steps: list[dict], tracker: dict, elapsed_s: float) -> None:
        buffer = io.BytesIO()
        torch.save({"rows": rows, "steps": steps, "tracker": tracker, "elapsed_s": elapsed_s}, buffer)
        write_atomic(self.path / STATE, buffer.getvalue())
        self.export(rows, steps)

    def export(self, rows: list[dict], steps: list[dict]) -> None:
        write_atomic(self.path / RESULTS_JSONL, _jsonl(rows))
        write_atomic(self.path / RESULTS_CSV, _csv(rows))
        write_atomic(self.path / STEPS_JSONL, _jsonl(steps))

    def load(self) -> dict | None:
        """What :meth:`save` stored last, or ``None`` for a run that has not finished a step."""
        if not (self.path / STATE).is_file():
            return None
        return torch.load(self.path / STATE, weights_only=False)

    def rows(self) -> list[dict]:
        """The per-frame results as written (for reports and tests)."""
        text = (self.path / RESULTS_JSONL).read_text() if (self.path / RESULTS_JSONL).is_file() else ""
        return [json.loads(line) for line in text.splitlines() if line]

    def write_summary(self, summary: dict) -> None:
        write_atomic(self.path / SUMMARY, json.dumps(summary, indent=2))
