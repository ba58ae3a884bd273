"""``ns-invert-bench grid --ray``: grids of tiny inversions on a real local Ray with 2 CPUs give the local
runner's table, survive a worker killed in the middle of a cell, record a failing cell, continue after an
interrupted driver, and run a cell from what they send it alone."""

import csv
import json
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil
import pytest
import ray
import torch
import yaml

from nerfinv_plugin.bench.grid import Bench, Grid, GridEvents, grid_from_dict, read_grid
from nerfinv_plugin.bench.ray_runner import (
    TASK_PREFIX,
    RayRunner,
    SentCell,
    model_files,
    read_files,
    receive,
    run_sent_cell,
    sequence_files,
)
from nerfinv_plugin.bench.tables import GRID_CSV, GRID_JSON, TABLE_MD
from nerfinv_plugin.cli.bench import entrypoint
from nerfinv_plugin.inversion.session import Events
from nerfinv_plugin.results.folder import CONFIG, STATE, STEPS_JSONL, SUMMARY, RunFolder
from nerfinv_plugin.results.records import StepRow

TINY = {"stop": 2, "pixels": 64, "eval_pixels": 128, "device": "cpu", "target": [0.0, 0.0, 0.15],
        "starts": {"source": "truth-offset", "count": 2}, "optimizer.iterations": 3,
        "monte_carlo": {"keep": [1], "spawn": 1}}
"""Two frames, two candidates then two, three iterations: seconds per cell on the CPU."""
TIMES = ("wall_time_s", "time_per_frame_s", "time_to_5deg_s", "run")
"""Columns that differ between two runs of the same cells: clocks, and where the run folder is."""


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray with 2 CPUs for the module (starting one costs seconds); the runner uses it as found."""
    os.environ.setdefault("RAY_raylet_start_wait_time_s", "180")  # as the runner does: the machine is busy
    os.environ.setdefault("RAY_worker_niceness", "0")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture
def one_thread():
    """The local runner with one torch thread, as each Ray cell has: the same arithmetic, the same numbers."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _grid_data(toy_run, seeds=(0, 1), cases: dict | None = None, overrides: dict | None = None) -> dict:
    config, data = toy_run
    return {"name": "g", "overrides": TINY | (overrides or {}), "seeds": list(seeds),
            "cases": cases or {"toy": {"load_config": str(config), "sequence": f"{data}:test"}},
            "variants": {"random": {"sampling": "random"}, "region": {"sampling": "interest_region"}}}


def _grid(toy_run, seeds=(0, 1), cases: dict | None = None, overrides: dict | None = None) -> Grid:
    return grid_from_dict(_grid_data(toy_run, seeds, cases, overrides), "tiny", "g")


def _table(folder: Path) -> list[dict]:
    with open(folder / "g" / GRID_CSV) as f:
        return [{k: v for k, v in row.items() if k not in TIMES} for row in csv.DictReader(f)]


def _poses(run: Path) -> list[tuple]:
    return [(r.q, r.r, r.rotation_deg, r.loss) for r in RunFolder(run).rows()]


def test_a_grid_on_ray_gives_the_local_runners_table(toy_run, tmp_path, local_ray, one_thread):
    local = Bench(_grid(toy_run), tmp_path / "local").run()
    on_ray = Bench(_grid(toy_run), tmp_path / "ray", runner=RayRunner()).run()
    assert [r["status"] for r in on_ray] == ["done"] * 4
    assert _table(tmp_path / "ray") == _table(tmp_path / "local")
    assert [r["frames"] for r in _table(tmp_path / "ray")] == ["2"] * 4
    for here, there in zip(local, on_ray):
        assert _poses(Path(there["run"])) == _poses(Path(here["run"]))
        # The driver's folder is what a local run writes: its settings, and a summary that names it.
        assert (Path(there["run"]) / CONFIG).read_text() == \
            (Path(here["run"]) / CONFIG).read_text().replace(str(tmp_path / "local"), str(tmp_path / "ray"))
        assert RunFolder(Path(there["run"])).summary().run == there["run"]


def _kill_in_the_middle(label: str, killed: list[int], stop: threading.Event) -> None:
    """Kill (SIGKILL, by pid) the Ray worker that runs ``label``'s task once the cell has saved a step in the
    worker's own folder (a temporary folder of this machine) and before it ends."""
    title = f"ray::{TASK_PREFIX}{label}"
    pattern = f"nerfinv-cell-*/out/g/nerfinv/{label}"
    while not stop.is_set():
        begun = [p for p in Path(tempfile.gettempdir()).glob(pattern) if (p / STATE).is_file()]
        if begun and not (begun[0] / SUMMARY).is_file():
            for process in psutil.process_iter(["pid", "cmdline"]):
                if " ".join(process.info["cmdline"] or []).startswith(title):
                    process.kill()
                    killed.append(process.pid)
                    return
        time.sleep(0.02)


def test_a_worker_killed_in_a_cell_is_run_again_and_the_grid_completes(toy_run, tmp_path, local_ray):
    killed: list[int] = []
    stop = threading.Event()
    watcher = threading.Thread(target=_kill_in_the_middle, args=("toy-region-s0", killed, stop))
    watcher.start()
    longer = {"stop": None, "optimizer.iterations": 10}  # all 6 frames: a few seconds, to be killed in
    try:
        records = Bench(_grid(toy_run, (0,), overrides=longer), tmp_path, runner=RayRunner(retries=2)).run()
    finally:
        stop.set()
        watcher.join()
    assert len(killed) == 1 and not psutil.pid_exists(killed[0])
    assert [(r["cell"], r["status"], r["frames"]) for r in records] == [("toy-random-s0", "done", 6),
                                                                        ("toy-region-s0", "done", 6)]


def test_a_failing_cell_is_recorded_and_tried_again_next_time(toy_run, tmp_path, local_ray, monkeypatch, capsys):
    config, data = toy_run
    missing = tmp_path / "later"
    cases = {"toy": {"load_config": str(config), "sequence": f"{data}:test"},
             "later": {"load_config": str(config), "sequence": f"{missing}:test"}}
    (tmp_path / "grid.yml").write_text(yaml.safe_dump(_grid_data(toy_run, (0,), cases), sort_keys=False))

    def run_cli(*options: str) -> None:
        monkeypatch.setattr(sys, "argv", ["ns-invert-bench", "grid", str(tmp_path / "grid.yml"), "--out",
                                          str(tmp_path / "out"), *options])
        entrypoint()
    for bad, message in ((("--ray", "--ray-cpus", "0"), "--ray-cpus must be >= 1"),
                         (("--ray-retries", "1"), "apply to --ray")):
        with pytest.raises(SystemExit) as exit_info:
            run_cli(*bad)
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and message in err and len(err.strip().splitlines()) == 1
    run_cli("--ray")
    out = capsys.readouterr().out
    assert "Ray: 2 CPUs, 0 GPUs; 1 CPU(s) per cell" in out and "later-region-s0: failed: SequenceError" in out
    records = json.loads((tmp_path / "out" / "g" / GRID_JSON).read_text())["cells"]
    assert [(r["cell"], r["status"]) for r in records] == [
        ("toy-random-s0", "done"), ("toy-region-s0", "done"), ("later-random-s0", "failed"),
        ("later-region-s0", "failed")]
    # The error of the task, with the path as the driver knows it (not the worker's copy).
    assert records[2]["error"].startswith(f"SequenceError: {missing} does not exist; give a SHIRT trajectory")
    assert "- `later-random-s0`: `SequenceError" in (tmp_path / "out" / "g" / TABLE_MD).read_text()

    shutil.copytree(data, missing)
    again = Bench(read_grid(tmp_path / "grid.yml"), tmp_path / "out", runner=RayRunner()).run()
    assert [r["status"] for r in again] == ["done"] * 4
    assert [r["wall_time_s"] for r in again[:2]] == [r["wall_time_s"] for r in records[:2]]  # read back


def _steps(run: Path) -> list[StepRow]:
    return RunFolder(run).steps() if (run / STEPS_JSONL).is_file() else []


def test_an_interrupted_driver_keeps_finished_cells_and_continues(toy_run, tmp_path, local_ray):
    grid = _grid(toy_run)
    runs = tmp_path / "g" / "nerfinv"

    # A local run stopped after the first frame of its second cell, as in test_bench.py.
    def interrupt(cell) -> Events:
        def step(row: StepRow) -> None:
            if cell.label == "toy-region-s0":
                raise KeyboardInterrupt
        return Events(step=step)
    with pytest.raises(KeyboardInterrupt):
        Bench(grid, tmp_path, GridEvents(inversion=interrupt)).run()
    begun = _steps(runs / "toy-region-s0")
    assert len(begun) == 1 and not (runs / "toy-region-s0" / SUMMARY).is_file()

    # On Ray, the driver stopped as the first cell it runs comes back.
    def stop(record: dict) -> None:
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        Bench(grid, tmp_path, GridEvents(cell_end=stop), RayRunner()).run()
    assert "2 of 4 runs finished, 0 failed, 2 to run" in (tmp_path / "g" / TABLE_MD).read_text()
    kept = {p: p.stat().st_mtime_ns for p in runs.glob(f"*/{SUMMARY}")}
    assert len(kept) == 2

    records = Bench(grid, tmp_path, runner=RayRunner()).run()
    assert [(r["status"], r["frames"]) for r in records] == [("done", 2)] * 4
    assert {p: p.stat().st_mtime_ns for p in kept} == kept  # not run again
    # The cell begun locally went on from its saved step on Ray: its first step is the one run here.
    assert _steps(runs / "toy-region-s0")[0] == begun[0]


def test_with_shared_storage_tasks_write_in_place_and_a_begun_cell_resumes(toy_run, tmp_path, local_ray):
    grid = _grid(toy_run, seeds=(0,))
    runs = tmp_path / "g" / "nerfinv"

    def interrupt(cell) -> Events:
        def step(row: StepRow) -> None:
            if cell.label == "toy-random-s0":
                raise KeyboardInterrupt
        return Events(step=step)
    with pytest.raises(KeyboardInterrupt):
        Bench(grid, tmp_path, GridEvents(inversion=interrupt)).run()
    begun = _steps(runs / "toy-random-s0")
    assert len(begun) == 1
    records = Bench(grid, tmp_path, runner=RayRunner(shared_storage=True)).run()
    assert [(r["status"], r["frames"]) for r in records] == [("done", 2)] * 2
    assert _steps(runs / "toy-random-s0")[0] == begun[0]  # went on from the step saved here
    assert RunFolder(runs / "toy-region-s0").summary().run == str((runs / "toy-region-s0").absolute())


def test_a_task_runs_from_what_it_is_sent(toy_run, tmp_path, local_ray):
    config, data = toy_run
    model, scene = tmp_path / "driver" / "model", tmp_path / "driver" / "scene"
    shutil.copytree(config.parent, model)
    shutil.copytree(data, scene)
    grid = _grid(toy_run, seeds=(0,), cases={"c": {"load_config": str(model / CONFIG), "sequence": f"{scene}:test"}})
    bench = Bench(grid, tmp_path / "out")
    cell = bench.cells[0]
    cell_config = bench.configs[cell.label]
    inputs = [ray.put(read_files(model_files(cell_config.load_config))),
              ray.put(read_files(sequence_files(cell_config.sequence)))]
    (tmp_path / "driver").rename(tmp_path / "elsewhere")  # before the task opens anything
    job = SentCell(cell_config, str(bench.run_dir(cell)), str(Path.cwd()))
    outcome = ray.get(ray.remote(run_sent_cell).remote(job, *inputs))
    assert outcome.error is None and {SUMMARY, STEPS_JSONL, CONFIG} & set(outcome.files) == {SUMMARY, STEPS_JSONL}
    receive(bench.run_dir(cell), cell_config, outcome.files)
    record = bench.finished(cell)
    assert record["status"] == "done" and record["frames"] == 2
    summary = RunFolder(bench.run_dir(cell)).summary()
    assert (summary.model, summary.sequence) == (str(model / CONFIG), f"{scene}:test")
