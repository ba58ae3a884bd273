"""The grid's tables: ``grid.csv`` (one row per cell, for pandas or a spreadsheet), ``table.md`` (the
thesis' kind of table: successes k/n per variant and case) and ``grid.json`` (everything, with the grid
definition that produced it). They are rewritten atomically after every cell, so a reader never sees
half a table and an interrupted grid keeps the table of what finished."""

import csv
import io
import json
from pathlib import Path

from nerfinv_plugin.bench.scoring import ALL_CASES, SUCCESS_DEG, aggregate, under_key
from nerfinv_plugin.results.atomic import write_atomic

GRID_CSV = "grid.csv"
TABLE_MD = "table.md"
GRID_JSON = "grid.json"

CSV_COLUMNS = ("cell", "case", "variant", "seed", "status", "frames", "final_rotation_deg", "min_rotation_deg",
               "mean_rotation_deg", "final_translation_m", "final_translation_rel", "wall_time_s", "time_per_frame_s",
               "time_to_5deg_s", *(under_key(t) for t in SUCCESS_DEG), "error", "run")
"""Unfinished and failed cells leave the metric columns empty."""


def records_csv(records: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for record in records:
        writer.writerow(["" if record.get(c) is None else record[c] for c in CSV_COLUMNS])
    return out.getvalue()


def _number(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _runs(group: dict) -> str:
    """Finished of all cells; failures named, since they shrink n without being the method's fault."""
    return f"{group['done']}/{group['cells']}" + (f", {group['failed']} failed" if group["failed"] else "")


def _table_row(group: dict) -> str:
    done = group["done"]
    successes = [f"{group['successes'][under_key(t)]}/{done}" if done else "-" for t in SUCCESS_DEG]
    case = f"**{ALL_CASES}**" if group["case"] == ALL_CASES else group["case"]
    cells = [group["variant"], case, _runs(group), *successes, _number(group["median_final_rotation_deg"], 2),
             _number(group["median_final_translation_m"], 3), _number(group["mean_time_per_frame_s"], 1),
             _number(group["mean_wall_time_s"], 0)]
    return "| " + " | ".join(cells) + " |"


def _ordered_groups(records: list[dict]) -> list[dict]:
    """Each variant's cases, then its totals over all cases (only when there is more than one case)."""
    by_case, by_variant = aggregate(records, by_case=True), aggregate(records, by_case=False)
    groups = []
    for total in by_variant:
        cases = [g for g in by_case if g["variant"] == total["variant"]]
        groups += cases + ([total] if len(cases) > 1 else [])
    return groups


def table_markdown(name: str, records: list[dict]) -> str:
    count = {status: sum(r["status"] == status for r in records) for status in ("done", "failed", "pending")}
    header = ["variant", "case", "runs done", *(f"< {t:g} deg" for t in SUCCESS_DEG),
              "median final rotation error (deg)", "median final translation error (m)",
              "mean time per frame (s)", "mean run time (s)"]
    lines = [f"# Grid `{name}`", "",
             f"{count['done']} of {len(records)} runs finished, {count['failed']} failed, {count['pending']} to run. "
             "A run succeeds under a threshold when the rotation error of its last frame is below it; "
             "k/n counts the successes among the finished runs.", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += [_table_row(group) for group in _ordered_groups(records)]
    failed = [r for r in records if r["status"] == "failed"]
    if failed:
        lines += ["", "## Failed cells (the next invocation tries them again)", ""]
        lines += [f"- `{r['cell']}`: `{r['error']}`" for r in failed]  # a code span keeps <scene> and | as text
    return "\n".join(lines) + "\n"


def write_tables(folder: Path, definition: dict, records: list[dict]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    write_atomic(folder / GRID_CSV, records_csv(records))
    write_atomic(folder / TABLE_MD, table_markdown(definition["name"], records))
    document = {"grid": definition, "thresholds_deg": list(SUCCESS_DEG), "cells": records,
                "by_case": aggregate(records, by_case=True), "by_variant": aggregate(records, by_case=False)}
    write_atomic(folder / GRID_JSON, json.dumps(document, indent=2))
