"""The report of a run: summary numbers by hand, the figures and the page from hand-written run files
(with and without ground truth, with the model gone), ``ns-invert-report`` on bad input, and the overlay
figures from a real tiny inversion."""

import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from nerfinv_plugin.cli.report import entrypoint
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.session import Inversion
from nerfinv_plugin.inversion.settings import InvertConfig, StartConfig, write_config
from nerfinv_plugin.report.build import REPORT_HTML, ReportError, write_report
from nerfinv_plugin.report.figures import evenly_spaced, step_points
from nerfinv_plugin.results.folder import RunFolder
from nerfinv_plugin.results.records import ErrorStatistics, FrameResult, RunSummary, StepRow
from nerfinv_plugin.results.summary import summarize

FIGURES = ("error_vs_time.png", "loss_error_per_iteration.png", "error_per_frame.png")
ERROR_FIGURES = ("error_vs_time.png", "error_per_frame.png")
IMAGE_FIGURES = ("overlays.png", "filmstrip.png")

ROTATION = (1.0, 5.0, 6.0, 12.0)
"""Rotation errors of the hand-made frames: 5.0 sits on a threshold, which does not count as under it."""
TRANSLATION_REL = (0.005, 0.05, 0.07, 0.2)


def _row(k: int, truth: bool, wall: float = 1.0) -> FrameResult:
    errors = {}
    if truth:
        errors = {"rotation_deg": ROTATION[k], "translation_m": 5 * TRANSLATION_REL[k],
                  "translation_rel": TRANSLATION_REL[k], "score": np.radians(ROTATION[k]) + TRANSLATION_REL[k]}
    return FrameResult(index=k, frame=2 * k, name=f"img<{k}>.png", steps=2, wall_time_s=wall,
                       elapsed_s=wall * (k + 1), q=[1.0, 0.0, 0.0, 0.0], r=[0.0, 0.0, 5.0],
                       c2w_model=np.eye(4).tolist(), loss=0.01 / (k + 1), candidates=6, dropped=0, **errors)


def _step(k: int, within: int, truth: bool) -> StepRow:
    """Two steps per frame of 5 iterations; the history's last error differs from the frame's error, so
    a test can tell which one a figure used."""
    history = list(np.linspace(30.0, 20.0 + k + within, 5)) if truth else None
    return StepRow(index=k, frame=2 * k, step=2 * k + within, wall_time_s=0.5, candidates=6 - within, kept=2,
                   dropped=[], iterations=5, loss=0.01, best_loss_per_iteration=list(np.geomspace(0.1, 0.01, 5)),
                   best_error_deg_per_iteration=history, error_of_best_loss_per_iteration=history)


def _run(root: Path, truth: bool = True, frames: int = 4) -> Path:
    """A run folder written by hand as ns-invert writes it, with a model and data that do not exist."""
    run = root / "e" / "nerfinv" / "t"
    run.mkdir(parents=True)
    config = InvertConfig(load_config=root / "moved" / "config.yml", sequence=str(root / "gone:test"),
                          output_dir=root, name="e", timestamp="t", stride=2, steps_per_frame=2, device="cpu")
    write_config(run / "config.yml", config)
    folder = RunFolder(run)
    folder.export([_row(k, truth) for k in range(frames)],
                  [_step(k, within, truth) for k in range(frames) for within in (0, 1)])
    folder.write_summary(RunSummary(frames_done=frames, frames_total=frames, complete=True, model_step=999,
                                    device="cpu"))
    return run


def _png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 100 and image.shape[1] > 100, path
    return image


def test_summary_matches_hand_computed_numbers_and_skips_frames_without_truth():
    rows = [_row(0, True, 1.0), _row(1, True, 2.0), _row(1, False, 3.0), _row(2, True, 4.0), _row(3, True, 5.0)]
    s = summarize(rows)
    assert s.frames_done == 5 and s.frames_with_truth == 4
    assert s.wall_time_s == pytest.approx(15.0) and s.mean_time_per_frame_s == pytest.approx(3.0)
    assert s.rotation_deg == ErrorStatistics(mean=6.0, median=5.5, max=12.0, final=12.0)
    assert s.translation_rel.to_json() == pytest.approx({"mean": 0.08125, "median": 0.06, "max": 0.2, "final": 0.2})
    assert s.translation_m.mean == pytest.approx(5 * 0.08125)
    assert s.success_rotation == pytest.approx({"2deg": 0.25, "5deg": 0.25, "10deg": 0.75})
    assert s.success_translation == pytest.approx({"0.01": 0.25, "0.05": 0.25, "0.1": 0.75})
    assert s.final_loss == rows[-1].loss


def test_summary_without_truth_or_rows_has_no_error_numbers():
    s = summarize([_row(0, False, 2.0), _row(1, False, 4.0)])
    assert s.mean_time_per_frame_s == pytest.approx(3.0)
    assert not {"rotation_deg", "success_rotation", "frames_with_truth"} & s.to_json().keys()
    assert summarize([]).to_json() == {"frames_done": 0}


def test_error_vs_time_takes_frame_errors_from_results_and_others_from_the_history():
    rows = [_row(k, True) for k in range(2)]
    steps = [_step(k, within, True) for k in range(2) for within in (0, 1)] + [_step(2, 0, True)]
    p = step_points(rows, steps)
    assert p.time_s == pytest.approx([0.5, 1.0, 1.5, 2.0, 2.5])
    # frame 2 has no row yet (interrupted between its steps): its step is an intermediate one
    assert p.ends_frame.tolist() == [False, True, False, True, False]
    assert p.error_deg == pytest.approx([20.0, ROTATION[0], 21.0, ROTATION[1], 22.0])
    assert p.candidates.tolist() == [6, 5, 6, 5, 6]
    assert step_points([_row(0, False)], [_step(0, 0, False), _step(0, 1, False)]).time_s.size == 0


def test_evenly_spaced_keeps_first_and_last():
    assert evenly_spaced(10, 3) == [0, 4, 9]
    assert evenly_spaced(20, 8)[0] == 0 and evenly_spaced(20, 8)[-1] == 19 and len(evenly_spaced(20, 8)) == 8
    assert evenly_spaced(2, 8) == [0, 1] and evenly_spaced(0, 3) == []


def test_report_has_every_figure_and_the_summary(tmp_path):
    run = _run(tmp_path)
    page = write_report(run, overlays=False)
    assert page == run / REPORT_HTML
    text = page.read_text()
    for name in FIGURES:
        _png(run / "report" / name)
        assert f'src="report/{name}"' in text
    for name in IMAGE_FIGURES:
        assert not (run / "report" / name).exists()
    assert text.count("Not in this report: rendering was turned off") == 2
    assert "4 of 4 (complete)" in text
    # rotation mean / median / max / final, translation in % of range, success with counts
    assert re.search(r"rotation error \(deg\)</td><td>6\.00</td><td>5\.50</td><td>12\.00</td><td>12\.00<", text)
    assert re.search(r"range\)</td><td>8\.1\d</td><td>6\.00</td><td>20\.00</td><td>20\.00<", text)  # in %
    assert "rotation error under 2°</td><td>25% (1/4)" in text
    assert "rotation error under 10°</td><td>75% (3/4)" in text
    assert "translation error under 1% of range</td><td>25% (1/4)" in text
    assert "img&lt;3&gt;.png" in text and "img<3>.png" not in text  # escaped
    assert "steps_per_frame: 2" in text  # the settings
    assert "<script" not in text and "http" not in text  # opens from disk, with nothing to fetch


def test_report_without_truth_leaves_out_the_error_figures_and_says_so(tmp_path):
    run = _run(tmp_path, truth=False)
    (run / "report").mkdir()
    (run / "report" / "error_vs_time.png").write_bytes(b"stale")  # from an older report: must go
    text = write_report(run, overlays=False).read_text()
    for name in ERROR_FIGURES:
        assert not (run / "report" / name).exists()
        assert f'src="report/{name}"' not in text
    assert text.count("Not in this report: the sequence has no ground truth") == 2
    assert "No ground truth for these frames" in text and "under 2°" not in text
    _png(run / "report" / "loss_error_per_iteration.png")  # the loss needs no truth


def test_report_notes_a_missing_model_instead_of_failing(tmp_path):
    run = _run(tmp_path)
    text = write_report(run, overlays=True).read_text()
    for name in IMAGE_FIGURES:
        assert not (run / "report" / name).exists()
    assert text.count(f"no config file at {tmp_path / 'moved' / 'config.yml'}") == 2
    for name in FIGURES:
        assert f'src="report/{name}"' in text


def test_unknown_overlay_frame_is_refused(tmp_path):
    with pytest.raises(ReportError, match="frame.s. 3 not in this run"):
        write_report(_run(tmp_path), frames=[2, 3])  # frames are 0, 2, 4, 6 (stride 2)


def _cli(argv: list[str], monkeypatch, capsys) -> tuple[int | None, str, str]:
    monkeypatch.setattr(sys, "argv", ["ns-invert-report", *argv])
    try:
        entrypoint()
        code = None
    except SystemExit as exit_info:
        code = exit_info.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cli_refuses_a_folder_that_is_not_a_run_in_one_line(tmp_path, monkeypatch, capsys):
    code, _, err = _cli([str(tmp_path)], monkeypatch, capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "not an ns-invert run folder" in err


def test_cli_writes_the_report(tmp_path, monkeypatch, capsys):
    run = _run(tmp_path)
    code, out, _ = _cli([str(run), "--no-overlays"], monkeypatch, capsys)
    assert code is None and "report:" in out and (run / REPORT_HTML).is_file()


def test_overlays_and_filmstrip_of_a_real_inversion(toy_run, tmp_path):
    config_yml, data = toy_run
    config = InvertConfig(load_config=config_yml, sequence=f"{data}:test", stop=2, output_dir=tmp_path, name="e",
                          timestamp="t", device="cpu", pixels=64, eval_pixels=128,
                          starts=StartConfig(source="truth-offset", count=2), optimizer=OptimizerConfig(iterations=3))
    Inversion.create(config).run()
    run = tmp_path / "e" / "nerfinv" / "t"
    text = write_report(run).read_text()
    assert "Not in this report" not in text
    assert not (run / "report" / "latency_vs_time.png").exists()  # a Blender split has no timestamps
    for name in FIGURES + IMAGE_FIGURES:
        _png(run / "report" / name)
        assert f'src="report/{name}"' in text
