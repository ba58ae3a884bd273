"""The records of a run folder: round trips through JSON and through the files, the files' exact format,
run folders written before the newer keys existed, and the layering (``inversion`` never imports
``report``)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.results.folder import RESULTS_CSV, RESULTS_JSONL, STEPS_JSONL, SUMMARY, RunFolder
from nerfinv_plugin.results.records import BankSummary, ErrorStatistics, FrameResult, RunSummary, StepRow
from nerfinv_plugin.results.summary import summarize

PACKAGE = Path(__file__).resolve().parents[1] / "nerfinv_plugin"

FRAME_JSON = {"index": 1, "frame": 3, "name": "img000004.jpg", "steps": 2, "wall_time_s": 1.5, "elapsed_s": 4.25,
              "q": [0.5, 0.5, -0.5, 0.5], "r": [0.1, -0.2, 5.0], "c2w_model": [[1.0, 0.0, 0.0, 0.0]] * 4,
              "loss": 0.0123, "outline_loss": 0.041, "silhouette_weight": 0.25, "candidates": 9, "dropped": 1,
              "object_found": True, "reinitialized": True,
              "bank_added": 3, "interpolated": False, "observed_s": 15.0, "estimated_s": 18.5, "latency_s": 3.5,
              "rotation_deg": 2.5, "translation_m": 0.05, "translation_rel": 0.01, "score": 0.0536}
"""A line of results.jsonl as ns-invert writes it, keys in the file's order."""
STEP_JSON = {"index": 1, "frame": 3, "step": 3, "wall_time_s": 0.75, "candidates": 9, "kept": 3, "dropped": [4],
             "pruned": [2, 7], "iterations": 3, "loss": 0.0123, "reinitialized": False, "bank_added": 3,
             "best_loss_per_iteration": [0.05, 0.02, 0.0123], "best_error_deg_per_iteration": [9.0, 4.0, 2.0],
             "error_of_best_loss_per_iteration": [12.0, 5.0, 2.5]}
"""A line of steps.jsonl with ground truth."""
SUMMARY_JSON = {
    "run": "outputs/roe1/nerfinv/t", "model": "outputs/toy/config.yml", "model_step": 999, "sequence": "shirt/roe1",
    "sequence_format": "shirt", "frames_total": 2, "complete": True, "device": "cpu", "starts": "bank",
    "frames_without_object": 0, "frames_reinitialized": 1, "target_radius_m": 0.8,
    "bank": {"views": 642, "entries": 7704, "built_in_this_run": False, "render_s": 12.5, "cache": "~/.cache/b"},
    "frames_done": 2, "wall_time_s": 3.0, "mean_time_per_frame_s": 1.5, "final_loss": 0.0123, "frames_with_truth": 2,
    "rotation_deg": {"mean": 2.0, "median": 2.0, "max": 2.5, "final": 2.5},
    "translation_m": {"mean": 0.04, "median": 0.04, "max": 0.05, "final": 0.05},
    "translation_rel": {"mean": 0.008, "median": 0.008, "max": 0.01, "final": 0.01},
    "score": {"mean": 0.04, "median": 0.04, "max": 0.0536, "final": 0.0536},
    "success_rotation": {"2deg": 0.5, "5deg": 1.0, "10deg": 1.0},
    "success_translation": {"0.01": 0.5, "0.05": 1.0, "0.1": 1.0}}
"""summary.json of a finished bank run with ground truth."""


def _frame(**changes) -> FrameResult:
    return FrameResult.from_json({**FRAME_JSON, **changes})


def test_records_go_to_json_and_back_unchanged():
    no_truth = {"rotation_deg": None, "translation_m": None, "translation_rel": None, "score": None}
    for data in (FRAME_JSON, {**FRAME_JSON, **no_truth}):
        assert FrameResult.from_json(data).to_json() == data
        assert list(FrameResult.from_json(data).to_json()) == list(data)  # the file's key order
    history = {k: v for k, v in STEP_JSON.items() if "error" not in k}  # a frame without ground truth
    for data in (STEP_JSON, history):
        assert StepRow.from_json(data).to_json() == data and list(StepRow.from_json(data).to_json()) == list(data)
    summary = RunSummary.from_json(SUMMARY_JSON)
    assert summary.bank == BankSummary(views=642, entries=7704, built_in_this_run=False, render_s=12.5,
                                       cache="~/.cache/b")
    assert summary.rotation_deg == ErrorStatistics(mean=2.0, median=2.0, max=2.5, final=2.5)
    assert summary.to_json() == SUMMARY_JSON and list(summary.to_json()) == list(SUMMARY_JSON)
    assert RunSummary.from_json(summary.to_json()) == summary


def test_what_the_run_folder_writes_reads_back_equal_in_the_files_format(tmp_path):
    rows = [_frame(index=0, frame=0), _frame(rotation_deg=None, translation_m=None, translation_rel=None, score=None)]
    steps = [StepRow.from_json(STEP_JSON), StepRow.from_json({k: v for k, v in STEP_JSON.items() if "error" not in k})]
    folder = RunFolder(tmp_path)
    folder.save(rows, steps, {"step": 2}, 4.25)
    folder.write_summary(RunSummary.from_json(SUMMARY_JSON))
    assert folder.rows() == rows and folder.steps() == steps
    assert folder.summary() == RunSummary.from_json(SUMMARY_JSON)
    saved = folder.load()
    assert (saved.rows, saved.steps, saved.tracker, saved.elapsed_s) == (rows, steps, {"step": 2}, 4.25)
    # byte for byte what the dictionaries ns-invert wrote before the records gave
    assert (tmp_path / RESULTS_JSONL).read_text() == "".join(json.dumps(r.to_json()) + "\n" for r in rows)
    assert (tmp_path / RESULTS_JSONL).read_text().splitlines()[0] == json.dumps({**FRAME_JSON, "index": 0, "frame": 0})
    assert (tmp_path / STEPS_JSONL).read_text().splitlines()[0] == json.dumps(STEP_JSON)
    assert (tmp_path / SUMMARY).read_text() == json.dumps(SUMMARY_JSON, indent=2)
    csv_lines = (tmp_path / RESULTS_CSV).read_text().splitlines()
    assert csv_lines[1] == "0,img000004.jpg,2,1.5,4.25,0.0123,0.041,0.25,2.5,0.05,0.01,0.0536,9,1,True,True,3," \
                           "False,15.0,18.5,3.5,0.5,0.5,-0.5,0.5,0.1,-0.2,5.0"
    assert csv_lines[2].startswith("3,img000004.jpg,2,1.5,4.25,0.0123,0.041,0.25,,,,,9,")


def test_an_old_run_folder_reads_with_defaults_for_the_newer_keys(tmp_path):
    old_frame = {k: v for k, v in FRAME_JSON.items()
                 if k not in ("object_found", "reinitialized", "bank_added", "outline_loss", "silhouette_weight")}
    old_step = {k: v for k, v in STEP_JSON.items() if k not in ("pruned", "iterations", "reinitialized", "bank_added")}
    old_summary = {k: v for k, v in SUMMARY_JSON.items()
                   if k not in ("starts", "frames_without_object", "frames_reinitialized", "target_radius_m", "bank")}
    (tmp_path / RESULTS_JSONL).write_text(json.dumps(old_frame) + "\n")
    (tmp_path / STEPS_JSONL).write_text(json.dumps(old_step) + "\n")
    (tmp_path / SUMMARY).write_text(json.dumps(old_summary))
    folder = RunFolder(tmp_path)
    (row,), (step,), summary = folder.rows(), folder.steps(), folder.summary()
    assert (row.object_found, row.reinitialized, row.bank_added) == (True, False, 0)
    assert row.outline_loss is None and row.silhouette_weight is None
    assert (step.pruned, step.iterations, step.reinitialized, step.bank_added) == ([], 3, False, 0)
    assert summary.bank is None and summary.starts is None and summary.frames_done == 2
    assert summary.to_json() == old_summary  # nothing made up for what the old run did not record


def test_an_unknown_key_is_an_error_and_a_cut_summary_reads_as_not_written(tmp_path):
    with pytest.raises(ValueError, match="unknown key.*colour"):
        FrameResult.from_json({**FRAME_JSON, "colour": "red"})
    with pytest.raises(ValueError, match="unknown key"):
        StepRow.from_json({**STEP_JSON, "typo": 1})
    (tmp_path / SUMMARY).write_text(json.dumps(SUMMARY_JSON, indent=2)[:100])
    assert RunFolder(tmp_path).summary() is None
    assert RunFolder(tmp_path / "missing").rows() == [] and RunFolder(tmp_path / "missing").summary() is None


def test_a_stored_summary_takes_the_numbers_of_newer_rows_and_keeps_the_rest():
    stored = RunSummary(frames_done=1, frames_total=3, complete=False, device="cpu")
    fresh = summarize([_frame(index=0), _frame(index=1, rotation_deg=3.5)])
    merged = stored.updated(fresh)
    assert (merged.frames_done, merged.frames_total, merged.device) == (2, 3, "cpu")
    assert merged.rotation_deg == fresh.rotation_deg and merged.success_rotation == {"2deg": 0.0, "5deg": 1.0,
                                                                                      "10deg": 1.0}


def test_write_atomic_makes_the_folder_and_leaves_no_temporary_file(tmp_path):
    write_atomic(tmp_path / "a" / "b.json", '{"x": 1}')
    write_atomic(tmp_path / "a" / "b.json", b'{"x": 2}')
    assert json.loads((tmp_path / "a" / "b.json").read_text()) == {"x": 2}
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["b.json"]


def test_inversion_does_not_import_report():
    """``report`` sits above ``inversion``; both use ``results``, which imports neither."""
    for source in sorted((PACKAGE / "inversion").glob("*.py")) + sorted((PACKAGE / "results").glob("*.py")):
        text = source.read_text()
        assert "nerfinv_plugin.report" not in text and "nerfinv_plugin.bench" not in text, source
    for source in sorted((PACKAGE / "results").glob("*.py")):
        assert "nerfinv_plugin.inversion" not in source.read_text(), source
    modules = [f"nerfinv_plugin.inversion.{p.stem}" for p in sorted((PACKAGE / "inversion").glob("*.py"))]
    code = (f"import importlib, sys\nfor m in {modules!r}: importlib.import_module(m)\n"
            "print(sorted(m for m in sys.modules if m.startswith(('nerfinv_plugin.report', 'nerfinv_plugin.bench'))))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]", done.stdout
