"""``ns-invert-bench grid``: success counting and aggregation against hand-computed numbers, grid files, and
grids of tiny inversions that are interrupted, resumed, and carry on past a failing cell."""

import csv
import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from nerfinv_plugin.bench.grid import Bench, GridError, GridEvents, expand, grid_from_dict, parse_overrides, read_grid
from nerfinv_plugin.bench.plots import FINAL_ERROR_PNG, PIXELS_PNG, SUCCESS_PNG, write_plots
from nerfinv_plugin.bench.scoring import ScoringError, aggregate, cell_metrics
from nerfinv_plugin.bench.tables import GRID_CSV, GRID_JSON, TABLE_MD, table_markdown, write_tables
from nerfinv_plugin.cli.bench import GridBench, entrypoint
from nerfinv_plugin.inversion.session import Events
from nerfinv_plugin.inversion.settings import SettingsError, presets_dir, to_dict
from nerfinv_plugin.results.records import FrameResult, StepRow

TINY = {"stop": 2, "pixels": 64, "eval_pixels": 128, "device": "cpu", "target": [0.0, 0.0, 0.15],
        "starts": {"source": "truth-offset", "count": 2}, "optimizer.iterations": 3,
        "monte_carlo": {"keep": [1], "spawn": 1}}
"""Two frames, two candidates then two, three iterations: seconds per cell on the CPU."""


def _row(rotation: float | None, wall: float, elapsed: float, translation: float = 0.1) -> FrameResult:
    """A frame's result with the errors and times given; what scoring does not read is filler."""
    return FrameResult(index=0, frame=0, name="f.png", steps=1, wall_time_s=wall, elapsed_s=elapsed,
                       q=[1.0, 0.0, 0.0, 0.0], r=[0.0, 0.0, 5.0], c2w_model=[], loss=0.01, candidates=1, dropped=0,
                       rotation_deg=rotation, translation_m=translation, translation_rel=translation / 5)


def test_success_is_the_last_frame_under_each_threshold():
    recovered = cell_metrics([_row(30.0, 10.0, 10.0), _row(4.0, 2.0, 12.0), _row(1.5, 2.0, 14.0, 0.02)])
    assert recovered == {
        "frames": 3, "final_rotation_deg": 1.5, "min_rotation_deg": 1.5, "mean_rotation_deg": pytest.approx(35.5 / 3),
        "final_translation_m": 0.02, "final_translation_rel": 0.004, "wall_time_s": 14.0,
        "time_per_frame_s": pytest.approx(14 / 3), "time_to_5deg_s": 12.0,
        "under_2deg": True, "under_3deg": True, "under_5deg": True, "under_10deg": True}
    lost = cell_metrics([_row(1.0, 3.0, 3.0), _row(6.0, 1.0, 4.0)])  # close on the way does not count
    assert (lost["min_rotation_deg"], lost["final_rotation_deg"], lost["time_to_5deg_s"]) == (1.0, 6.0, 3.0)
    assert [lost[k] for k in ("under_2deg", "under_3deg", "under_5deg", "under_10deg")] == [False, False, False, True]
    on_the_line = cell_metrics([_row(5.0, 1.0, 1.0)])  # "less than": a threshold itself is not under it
    assert (on_the_line["under_5deg"], on_the_line["under_10deg"], on_the_line["time_to_5deg_s"]) == (False, True, None)
    with pytest.raises(ScoringError, match="true pose"):
        cell_metrics([_row(None, 1.0, 1.0)])
    with pytest.raises(ScoringError, match="no frame"):
        cell_metrics([])


def _done(variant: str, case: str, seed: int, final: float, time_s: float = 2.0) -> dict:
    return {"cell": f"{case}-{variant}-s{seed}", "case": case, "variant": variant, "seed": seed, "status": "done",
            "run": "r", **cell_metrics([_row(final, time_s, time_s)])}


def _other(variant: str, case: str, seed: int, status: str) -> dict:
    return {"cell": f"{case}-{variant}-s{seed}", "case": case, "variant": variant, "seed": seed, "status": status,
            "run": "r", **({"error": "SequenceError: no such sequence"} if status == "failed" else {})}


RECORDS = [_done("a", "x", 0, 1.0, 2.0), _done("a", "x", 1, 4.0, 4.0), _done("a", "x", 2, 12.0, 6.0),
           _done("a", "y", 0, 2.5, 8.0), _other("a", "y", 1, "failed"), _other("a", "y", 2, "pending"),
           _done("b", "x", 0, 20.0), _done("b", "y", 0, 0.5)]


def test_aggregation_counts_k_of_n_finished_runs_per_case_and_per_variant():
    by_case = {(g["variant"], g["case"]): g for g in aggregate(RECORDS, by_case=True)}
    ax, ay = by_case["a", "x"], by_case["a", "y"]
    assert (ax["cells"], ax["done"], ax["failed"]) == (3, 3, 0)
    assert ax["successes"] == {"under_2deg": 1, "under_3deg": 1, "under_5deg": 2, "under_10deg": 2}
    assert ax["median_final_rotation_deg"] == 4.0 and ax["mean_wall_time_s"] == 4.0
    assert (ay["cells"], ay["done"], ay["failed"]) == (3, 1, 1)
    assert ay["successes"] == {"under_2deg": 0, "under_3deg": 1, "under_5deg": 1, "under_10deg": 1}
    a, b = aggregate(RECORDS, by_case=False)
    assert (a["variant"], a["cells"], a["done"], a["failed"]) == ("a", 6, 4, 1)
    assert a["successes"] == {"under_2deg": 1, "under_3deg": 2, "under_5deg": 3, "under_10deg": 3}
    assert a["median_final_rotation_deg"] == 3.25 and a["mean_time_per_frame_s"] == 5.0
    assert b["successes"]["under_5deg"] == 1 and b["done"] == 2

    table = table_markdown("g", RECORDS)
    assert "6 of 8 runs finished, 1 failed, 1 to run" in table
    assert "| a | x | 3/3 | 1/3 | 1/3 | 2/3 | 2/3 | 4.00 | 0.100 | 4.0 | 4 |" in table
    assert "| a | y | 1/3, 1 failed | 0/1 | 1/1 | 1/1 | 1/1 | 2.50 |" in table
    assert "| a | **all cases** | 4/6, 1 failed | 1/4 | 2/4 | 3/4 | 3/4 | 3.25 |" in table
    assert "| b | **all cases** | 2/2 | 1/2 | 1/2 | 1/2 | 1/2 | 10.25 |" in table
    assert "- `y-a-s1`: `SequenceError: no such sequence`" in table


def test_tables_and_figures_are_written(tmp_path):
    pixels = [_done(f"px{n}", case, seed, final, time_s) for n, final, time_s in ((64, 9.0, 1.0), (256, 3.0, 2.0))
              for case in ("x", "y") for seed in (0, 1)]
    write_tables(tmp_path, {"name": "g"}, RECORDS + pixels)
    with open(tmp_path / GRID_CSV) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(RECORDS) + len(pixels)
    assert rows[1]["final_rotation_deg"] == "4.0" and rows[1]["under_5deg"] == "True"
    assert rows[5]["status"] == "pending" and rows[5]["final_rotation_deg"] == ""
    saved = json.loads((tmp_path / GRID_JSON).read_text())
    assert saved["thresholds_deg"] == [2.0, 3.0, 5.0, 10.0] and len(saved["by_variant"]) == 4
    written = write_plots(tmp_path, "g", RECORDS + pixels, {"px64": 64, "px256": 256})
    assert [p.name for p in written] == [SUCCESS_PNG, FINAL_ERROR_PNG, PIXELS_PNG]
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in written)
    assert write_plots(tmp_path / "none", "g", [_other("a", "x", 0, "pending")], {}) == []


def test_overrides_merge_dotted_and_nested_keys_and_refuse_what_the_grid_sets():
    assert expand({"starts": {"source": "volume"}, "starts.count": 20, "monte-carlo.reset-lr": False}, "w") == \
        {"starts": {"source": "volume", "count": 20}, "monte_carlo": {"reset_lr": False}}
    assert parse_overrides(["device=cuda", "monte_carlo.keep=[5, 5]", "stop=3"], "w") == \
        {"device": "cuda", "monte_carlo": {"keep": [5, 5]}, "stop": 3}
    with pytest.raises(GridError, match="seed cannot be overridden"):
        expand({"seed": 3}, "w")
    with pytest.raises(GridError, match="KEY=VALUE"):
        parse_overrides(["device"], "w")


def _grid_data(**changes) -> dict:
    data = {"cases": {"c": {"load_config": "m/config.yml", "sequence": "s"}}, "variants": {"v": {"pixels": 64}}}
    return {**data, **changes}


@pytest.mark.parametrize("data, error, match", [
    (_grid_data(seed=[1]), GridError, "unknown key"),
    (_grid_data(cases={"c": {"load_config": "m"}}), GridError, "needs sequence"),
    (_grid_data(variants={"a/b": {}}), GridError, "label 'a/b'"),
    (_grid_data(seeds=[0, 0]), GridError, "distinct"),
    (_grid_data(variants={"v": {"pixles": 64}}), SettingsError, "variant v: unknown option 'pixles'"),
    (_grid_data(preset="no-such-preset"), SettingsError, "no preset"),
])
def test_bad_grid_files_are_refused_before_anything_runs(data, error, match, tmp_path):
    with pytest.raises(error, match=match):
        Bench(grid_from_dict(data, "grid.yml", "g"), tmp_path)
    assert not (tmp_path / "g").exists()


def test_the_thesis_grids_build_every_cell(tmp_path):
    grids = sorted((presets_dir() / "bench").glob("*.yml"))
    assert {g.stem for g in grids} >= {"sampling", "pixels", "lr-reset", "far-starts", "toy-vs-spacecraft",
                                       "thesis-counts"}
    thesis = {"sampling", "pixels", "lr-reset", "far-starts", "toy-vs-spacecraft", "thesis-counts"}
    for path in grids:
        bench = Bench(read_grid(path), tmp_path)
        assert len(bench.grid.variants) >= 2, path
        if path.stem in thesis:  # counted as the thesis does: 3 trajectories, 10 runs each
            assert len(bench.grid.seeds) == 10 and len(bench.grid.cases) >= 3, path
        configs = list(bench.configs.values())
        assert len({(c.sequence, c.start, c.stop) for c in configs}) == len(bench.grid.cases), path
        first = [bench.configs[c.label] for c in bench.cells
                 if c.seed == bench.grid.seeds[0] and c.case is bench.grid.cases[0]]
        settings = {json.dumps(to_dict(replace(c, timestamp=None))) for c in first}
        assert len(settings) == len(bench.grid.variants), path  # every variant changes something


def _tiny_grid(toy_run, cases: dict | None = None) -> dict:
    config, data = toy_run
    return {"name": "g", "overrides": TINY, "seeds": [0, 1],
            "cases": cases or {"toy": {"load_config": str(config), "sequence": f"{data}:test"}},
            "variants": {"random": {"sampling": "random"}, "region": {"sampling": "interest_region"}}}


def _files(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.iterdir())}


def test_an_interrupted_grid_resumes_and_runs_only_the_missing_cells(toy_run, tmp_path):
    grid = grid_from_dict(_tiny_grid(toy_run), "tiny", "g")
    started: list[tuple[str, bool]] = []

    def interrupt_second_cell(cell) -> Events:
        def step(row: StepRow) -> None:
            if cell.label == "toy-region-s0":
                raise KeyboardInterrupt
        return Events(step=step)

    with pytest.raises(KeyboardInterrupt):
        Bench(grid, tmp_path, GridEvents(cell_start=lambda c, r: started.append((c.label, r)),
                                         inversion=interrupt_second_cell)).run()
    folder = tmp_path / "g"
    assert started == [("toy-random-s0", False), ("toy-region-s0", False)]
    assert "1 of 4 runs finished, 0 failed, 3 to run" in (folder / TABLE_MD).read_text()
    first = _files(folder / "nerfinv" / "toy-random-s0")
    assert (folder / "nerfinv" / "toy-region-s0" / "state.pt").is_file()  # stopped after its first frame

    started.clear()
    records = Bench(grid, tmp_path, GridEvents(cell_start=lambda c, r: started.append((c.label, r)))).run()
    assert started == [("toy-region-s0", True), ("toy-random-s1", False), ("toy-region-s1", False)]
    assert _files(folder / "nerfinv" / "toy-random-s0") == first
    with open(folder / GRID_CSV) as f:
        rows = list(csv.DictReader(f))
    assert [(r["cell"], r["status"], r["frames"]) for r in rows] == [
        (c, "done", "2") for c in ("toy-random-s0", "toy-region-s0", "toy-random-s1", "toy-region-s1")]
    assert all(0 <= float(r["final_rotation_deg"]) < 180 for r in rows)
    assert [r["cell"] for r in records] == [r["cell"] for r in rows]
    assert "4 of 4 runs finished" in (folder / TABLE_MD).read_text()
    assert (folder / SUCCESS_PNG).is_file() and (folder / FINAL_ERROR_PNG).is_file()

    # An edited variant does not count (or continue) the runs made with the old settings.
    edited = grid_from_dict(_tiny_grid(toy_run) | {"variants": {"random": {"sampling": "random", "pixels": 32},
                                                                "region": {"sampling": "interest_region"}}}, "t", "g")
    records = Bench(edited, tmp_path).run()
    assert [r["status"] for r in records] == ["failed", "done", "failed", "done"]
    assert "other settings (pixels 64 -> 32)" in records[0]["error"]


def test_a_failing_cell_is_recorded_and_tried_again_while_the_others_complete(toy_run, tmp_path, monkeypatch,
                                                                                capsys):
    config, data = toy_run
    grid = {**_tiny_grid(toy_run, {"toy": {"load_config": str(config), "sequence": f"{data}:test"},
                                   "gone": {"load_config": str(config), "sequence": str(tmp_path / "nope")}}),
            "seeds": [0], "variants": {"region": {}}}
    (tmp_path / "grid.yml").write_text(yaml.safe_dump(grid, sort_keys=False))
    monkeypatch.setattr(sys, "argv", ["ns-invert-bench", "grid", str(tmp_path / "grid.yml"),
                                      "--out", str(tmp_path / "out")])
    entrypoint()
    out = capsys.readouterr().out
    assert "gone-region-s0: failed: SequenceError" in out and "toy-region-s0: final rotation error" in out
    records = json.loads((tmp_path / "out" / "g" / GRID_JSON).read_text())["cells"]
    assert [(r["cell"], r["status"]) for r in records] == [("toy-region-s0", "done"), ("gone-region-s0", "failed")]
    assert "\n" not in records[1]["error"] and str(tmp_path / "nope") in records[1]["error"]
    assert "- `gone-region-s0`: `SequenceError" in (tmp_path / "out" / "g" / TABLE_MD).read_text()

    started: list[str] = []
    again = Bench(read_grid(tmp_path / "grid.yml"), tmp_path / "out", GridEvents(cell_start=lambda c, r:
                                                                                  started.append(c.label))).run()
    assert started == ["gone-region-s0"] and [r["status"] for r in again] == ["done", "failed"]


def test_command_line_replacements_bad_input_and_ctrl_c(tmp_path, monkeypatch, capsys):
    data = {**_grid_data(), "cases": {"c": {"load_config": "m/config.yml", "sequence": "s",
                                            "overrides": {"target": [0.0, 0.0, 0.2]}}},
            "overrides": {"stop": 9, "starts": {"count": 4}}}
    (tmp_path / "grid.yml").write_text(yaml.safe_dump(data))
    command = GridBench(grid=tmp_path / "grid.yml", case=(("c", "other/config.yml", "t"), ("d", "x.yml", "u")),
                           seeds=(3, 4), override=("device=cuda", "starts.source=volume"))
    grid = command.load()
    assert [(c.label, str(c.load_config), c.sequence, c.overrides) for c in grid.cases] == [
        ("c", "other/config.yml", "t", {"target": [0.0, 0.0, 0.2]}), ("d", "x.yml", "u", {})]
    assert grid.seeds == [3, 4]
    assert grid.overrides == {"stop": 9, "starts": {"count": 4, "source": "volume"}, "device": "cuda"}

    def run_cli(*argv: str) -> tuple[int, str]:
        monkeypatch.setattr(sys, "argv", ["ns-invert-bench", "grid", str(tmp_path / "grid.yml"), *argv])
        with pytest.raises(SystemExit) as exit_info:
            entrypoint()
        return exit_info.value.code, capsys.readouterr().err

    code, err = run_cli("--override", "pixles=3")
    assert code == 2 and "unknown option 'pixles'" in err and len(err.strip().splitlines()) == 1

    def interrupted(self) -> list[dict]:
        raise KeyboardInterrupt
    monkeypatch.setattr(Bench, "run", interrupted)
    code, err = run_cli("--out", str(tmp_path))
    assert code == 130 and "Run the same command again" in err

