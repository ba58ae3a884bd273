"""The run's clock (``--clock frames | realtime``), interpolated frames and the latency figures: the schedule
against hand-worked tables, SE(3) interpolation against hand-built poses, the latency fields of the results,
and a realtime run on the toy model that resumes to the numbers of an uninterrupted one."""

import csv
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro

from nerfinv_plugin.bench.perf import LatencyRun, latency_rows
from nerfinv_plugin.cli.bench import Commands
from nerfinv_plugin.cli.invert import _frame_line, _summary_lines
from nerfinv_plugin.data.sequences import read_sequence
from nerfinv_plugin.geometry.se3 import rotation_about
from nerfinv_plugin.inversion.clock import Clock, interpolated_pose
from nerfinv_plugin.inversion.optimizer import IterationRecord, OptimizerConfig
from nerfinv_plugin.inversion.session import Events, Inversion, InversionError
from nerfinv_plugin.inversion.settings import InvertConfig, StartConfig
from nerfinv_plugin.inversion.tracker import MonteCarloConfig
from nerfinv_plugin.report.build import write_report
from nerfinv_plugin.results.folder import RunFolder
from nerfinv_plugin.results.records import FrameResult, RunSummary
from nerfinv_plugin.results.summary import summarize
from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.trajectories import TrajectorySpec

SPACING = [5.0 * k for k in range(10)]


def _drive(clock: Clock, iterations: list[int], setup_s: float = 0.0) -> list[tuple[int, float, float]]:
    """Run the clock as ``Inversion.run`` does, a step of ``iterations[i]`` iterations (and no compute
    time) at the i-th visit: ``(frame, start, end)`` of every step."""
    clock.charge(setup_s)
    table = []
    for i, k in enumerate(clock.visits()):
        start = clock.now_s
        clock.charge(0.0, iterations[i])
        table.append((k, start, clock.now_s))
    return table


def test_realtime_clock_takes_the_newest_frame_and_waits_when_none_is_new():
    # Frames every 5 s; 0.5 s per iteration. Worked by hand:
    #   frame 0 at 0: 30 it -> 15 s, ends 15; newest observed at 15 is frame 3 (15 s): 1 and 2 skipped
    #   frame 3 from 15: 4 it -> 2 s, ends 17; nothing new (frame 4 comes at 20): wait
    #   frame 4 from 20: 4 it, ends 22; wait for frame 5 (25)
    #   frame 5 from 25: 20 it -> 10 s, ends 35; newest is 7 (35 s, observed just then): 6 skipped
    #   frame 7 from 35: 8 it, ends 39; newest is 7: wait for 8 (40)
    #   frame 8 from 40: 30 it, ends 55; newest is 9 (45), the last
    #   frame 9 from 55: 2 it, ends 56; the sequence is done
    clock = Clock("realtime", 10, SPACING, cost_s=0.5)
    table = _drive(clock, [30, 4, 4, 20, 8, 30, 2], setup_s=100.0)  # a fixed cost charges only iterations
    assert table == [(0, 0.0, 15.0), (3, 15.0, 17.0), (4, 20.0, 22.0), (5, 25.0, 35.0), (7, 35.0, 39.0),
                     (8, 40.0, 55.0), (9, 55.0, 56.0)]


def test_clock_speed_divides_compute_and_measured_time_is_charged():
    # 0.1: a computer ten times slower. 0.6 s of setup is 6 s: frame 1 (5 s) is the newest after the first
    # step (0.2 s -> 2 s, ends 8 s); 1.5 s of compute (15 s) from 8 s ends at 23 s, when 4 (20 s) is newest.
    clock = Clock("realtime", 10, SPACING, speed=0.1)
    clock.charge(0.6)
    visits = clock.visits()
    assert next(visits) == 0 and clock.now_s == pytest.approx(6.0)
    assert clock.charge(0.2, iterations=60) == pytest.approx(2.0)  # measured time, whatever the iterations
    assert next(visits) == 1 and clock.now_s == pytest.approx(8.0)
    clock.charge(1.5)
    assert next(visits) == 4 and clock.now_s == pytest.approx(23.0)


def test_frames_clock_takes_every_frame_waiting_when_ahead_and_queueing_when_behind():
    clock = Clock("frames", 4, SPACING[:4], cost_s=1.0)
    # 2 s a step: ahead of the camera, it waits for each frame; 12 s a step: every frame still taken, late.
    assert _drive(clock, [2, 2, 12, 12]) == [(0, 0.0, 2.0), (1, 5.0, 7.0), (2, 10.0, 22.0), (3, 22.0, 34.0)]
    no_times = Clock("frames", 3, None, cost_s=1.0)  # a sequence without timestamps: no waiting
    assert _drive(no_times, [2, 2, 2]) == [(0, 0.0, 2.0), (1, 2.0, 4.0), (2, 4.0, 6.0)]
    with pytest.raises(ValueError, match="observation times"):
        Clock("realtime", 3, None)


def test_a_resumed_clock_replays_the_frames_taken_and_goes_on_from_the_recorded_time():
    whole = _drive(Clock("realtime", 10, SPACING, cost_s=0.5), [30, 4, 4, 20, 8, 30, 2])
    resumed = Clock("realtime", 10, SPACING, cost_s=0.5, now_s=whole[2][2])  # stopped after 3 steps
    visits = resumed.visits([k for k, _, _ in whole[:3]])
    assert [next(visits) for _ in range(3)] == [0, 3, 4]  # replayed as recorded, the clock untouched
    assert resumed.now_s == whole[2][2]
    rest = []
    for k, iterations in zip(visits, [20, 8, 30, 2]):
        start = resumed.now_s
        resumed.charge(0.0, iterations)
        rest.append((k, start, resumed.now_s))
    assert rest == whole[3:]


def _pose(rot_deg: float, axis: str, about: tuple[float, float, float], shift=(0.0, 0.0, 0.0)) -> torch.Tensor:
    angle = math.radians(rot_deg)
    c, s = math.cos(angle), math.sin(angle)
    rot = {"z": [[c, -s, 0], [s, c, 0], [0, 0, 1]], "x": [[1, 0, 0], [0, c, -s], [0, s, c]]}[axis]
    pose = rotation_about(torch.tensor(about, dtype=torch.float64), torch.tensor(rot, dtype=torch.float64))
    pose[:3, 3] += torch.tensor(shift, dtype=torch.float64)
    return pose


def test_interpolated_pose_turns_about_the_same_axis_at_a_constant_rate():
    camera = torch.eye(4, dtype=torch.float64)
    camera[:3, 3] = torch.tensor([0.0, 0.0, 5.0])  # 5 m from the target at the origin, looking at it
    about = (0.1, -0.2, 0.0)
    before = _pose(10.0, "z", about) @ camera
    after = _pose(70.0, "z", about) @ camera  # 60 degrees further about the same axis through ``about``
    for fraction, degrees in ((0.0, 10.0), (0.25, 25.0), (0.5, 40.0), (1.0, 70.0)):
        expected = _pose(degrees, "z", about) @ camera
        torch.testing.assert_close(interpolated_pose(before, after, fraction), expected, atol=1e-10, rtol=0)
    # A pure shift is interpolated linearly.
    moved = _pose(0.0, "z", about, shift=(0.4, 0.0, -1.0)) @ camera
    halfway = _pose(0.0, "z", about, shift=(0.1, 0.0, -0.25)) @ camera
    torch.testing.assert_close(interpolated_pose(camera, moved, 0.25), halfway, atol=1e-10, rtol=0)
    # The same curve in another world frame: a rigid change of frame commutes with the interpolation.
    frame = _pose(33.0, "x", (1.0, 2.0, 3.0), shift=(0.5, -0.5, 2.0))
    torch.testing.assert_close(interpolated_pose(frame @ before, frame @ after, 0.3),
                               frame @ interpolated_pose(before, after, 0.3), atol=1e-10, rtol=0)


def _row(k: int, rotation: float | None, *, interpolated: bool = False, observed: float | None = None,
         estimated: float | None = None) -> FrameResult:
    return FrameResult(index=k, frame=k, name=f"{k}.jpg", steps=0 if interpolated else 1,
                       wall_time_s=0.0 if interpolated else 2.0, elapsed_s=2.0 * k, q=[1, 0, 0, 0], r=[0, 0, 5],
                       c2w_model=np.eye(4).tolist(), loss=None if interpolated else 0.01 * (k + 1),
                       candidates=0 if interpolated else 6, dropped=0, interpolated=interpolated,
                       observed_s=observed, estimated_s=estimated,
                       latency_s=None if observed is None else estimated - observed,
                       rotation_deg=rotation, translation_m=None if rotation is None else 0.1,
                       translation_rel=None if rotation is None else 0.02, score=None if rotation is None else 0.1)


def test_latency_first_lock_and_skipped_frames_in_the_summary():
    rows = [_row(0, 30.0, observed=0.0, estimated=12.0),
            _row(1, 20.0, interpolated=True, observed=5.0, estimated=18.0),
            _row(2, 4.0, interpolated=True, observed=10.0, estimated=18.0),  # under 5 but not estimated
            _row(3, 8.0, observed=15.0, estimated=18.0),
            _row(4, 3.0, observed=20.0, estimated=23.0),
            _row(5, 2.0, observed=25.0, estimated=29.0)]
    summary = summarize(rows)
    assert summary.frames_done == 6 and summary.frames_estimated == 4 and summary.frames_skipped == 2
    assert summary.latency_s.mean == pytest.approx((12 + 3 + 3 + 4) / 4)  # the estimated frames' latency
    assert summary.latency_s.max == 12.0 and summary.latency_s.final == 4.0
    assert summary.time_to_first_lock_s == 23.0 and summary.first_lock_frame == 4
    assert summary.clock_end_s == 29.0
    assert summary.mean_time_per_frame_s == 2.0 and summary.final_loss == pytest.approx(0.06)
    assert summary.rotation_deg.mean == pytest.approx(67.0 / 6) and summary.frames_with_truth == 6
    estimated = summary.estimated_only
    assert estimated.frames == 4 and estimated.rotation_deg.mean == pytest.approx(43.0 / 4)
    assert estimated.success_rotation["5deg"] == 0.5 and summary.success_rotation["5deg"] == pytest.approx(0.5)
    assert RunSummary.from_json(json.loads(json.dumps(summary.to_json()))) == summary
    lines = "\n".join(_summary_lines(replace(summary, frames_total=6)))
    assert "latency" in lines and "2 of 6 frames skipped" in lines and "23.0 s (frame 4)" in lines
    assert "over the 4 estimated frames alone" in lines
    assert "skipped, pose interpolated" in _frame_line(rows[1]) and "latency 13.0 s" in _frame_line(rows[1])
    assert "latency 4.0 s" in _frame_line(rows[5])
    # No estimate under 5 degrees: no lock; no timestamps: no latency; nothing skipped: no second accuracy.
    plain = summarize([_row(0, 30.0, estimated=2.0), _row(1, 9.0, estimated=4.0)])
    assert plain.time_to_first_lock_s is None and plain.latency_s is None and plain.estimated_only is None
    assert plain.frames_skipped == 0


def test_latency_benchmark_rows_are_the_medians_over_the_runs_at_each_speed():
    def run(speed: float, latency: float, skipped: int, lock: float | None, rotation: float) -> LatencyRun:
        rows = [_row(0, rotation, observed=0.0, estimated=latency),
                _row(1, rotation, interpolated=skipped > 0, observed=5.0, estimated=5.0 + latency),
                _row(2, 1.0 if lock is not None else 9.0, observed=10.0, estimated=10.0 + latency)]
        summary = summarize(rows)
        return LatencyRun(speed, Path(f"run-{speed}-{latency}"), replace(summary, time_to_first_lock_s=lock))

    runs = [run(1.0, 2.0, 0, 12.0, 10.0), run(1.0, 4.0, 1, None, 20.0), run(1.0, 3.0, 1, 14.0, 30.0),
            run(0.1, 20.0, 1, None, 40.0)]
    fast, slow = latency_rows(runs)
    assert (fast.clock_speed, fast.runs, slow.runs) == (1.0, 3, 1)
    assert fast.mean_latency_s == 3.0 and fast.frames_skipped == 1.0  # medians of 2, 4, 3 and of 0, 1, 1
    assert fast.time_to_first_lock_s == 13.0 and fast.locked_runs == 2  # over the runs that locked
    assert slow.time_to_first_lock_s is None and slow.mean_latency_s == 20.0


def test_the_latency_benchmark_runs_ns_invert_with_its_options():
    bench = tyro.cli(Commands, args=["perf", "--load-config", "run/config.yml", "--sequence", "shirt/roe1", "--latency",
                                     "--preset", "shirt-synthetic", "--candidates", "7", "--iterations", "9",
                                     "--stop", "4", "--clock-speeds", "1", "0.1", "--out", "o"])
    config = bench.latency_config()
    assert bench.latency and bench.clock_speeds == (1.0, 0.1) and bench.latency_runs == 3
    assert (config.starts.count, config.optimizer.iterations, config.stop, config.pixels) == (7, 9, 4, 256)
    assert config.resolution == (240, 150) and config.preset == "shirt-synthetic"  # the rest from the preset
    assert (str(config.output_dir), config.name, str(config.sequence)) == ("o", "latency", "shirt/roe1")


def test_the_latency_benchmark_keeps_ns_inverts_own_counts_unless_given(tmp_path):
    """Unset, the candidates, pixels and iterations of the latency runs are ns-invert's (or the preset's): the
    bare command is what the latency target is about; the thesis' 15 x 256 x 60 is the loops' benchmark."""
    preset = tmp_path / "fast.yml"
    preset.write_text("pixels: 100\noptimizer: {iterations: 11}\n")
    args = ["perf", "--load-config", "run/config.yml", "--sequence", "shirt/roe1", "--latency"]
    bare = tyro.cli(Commands, args=args).latency_config()
    default = InvertConfig()
    assert (bare.starts.count, bare.pixels, bare.optimizer.iterations) == (
        default.starts.count, default.pixels, default.optimizer.iterations)
    preset_config = tyro.cli(Commands, args=args + ["--preset", str(preset)]).latency_config()
    assert (preset_config.pixels, preset_config.optimizer.iterations) == (100, 11)
    given = tyro.cli(Commands, args=args + ["--preset", str(preset), "--pixels", "64"]).latency_config()
    assert given.pixels == 64


@pytest.fixture(scope="module")
def shirt(toy_run, tmp_path_factory) -> Path:
    """A SHIRT root with a 6-frame roe1 trajectory of the toy scene (metadata.json: 5 s apart)."""
    out = tmp_path_factory.mktemp("clock")
    write_shirt_trajectories(out, "toy", [TrajectorySpec(kind="roe1", num_frames=6, range_m=5.0)],
                             speedplus_like_camera(80, 50), False, seed=0, spp=32, step=lambda: None)
    return out / "shirt"


def test_shirt_timestamps_come_from_metadata_and_the_interval_option(shirt):
    assert [f.time_s for f in read_sequence(shirt / "roe1").frames] == [0.0, 5.0, 10.0, 15.0, 20.0, 25.0]
    assert [f.time_s for f in read_sequence(shirt / "roe1", start=1, stride=2).frames] == [0.0, 10.0, 20.0]
    given = read_sequence(shirt / "roe1", stop=3, frame_interval_s=0.5)
    assert [f.time_s for f in given.frames] == [0.0, 0.5, 1.0] and given.frame_interval_s == 0.5


def _config(toy_run, shirt: Path, out: Path, **changes) -> InvertConfig:
    """Realtime, 9 s a step (6 iterations at 1.5 s) on frames 5 s apart: hand-worked, frame 0 ends at 9 s,
    when 1 is the newest; 1 ends at 18 s (newest: 3); 3 at 27 s (newest: 5, the last): 2 and 4 skipped."""
    config = InvertConfig(
        load_config=toy_run[0], sequence=str(shirt / "roe1"), output_dir=out, name="e", timestamp="t",
        device="cpu", target=(0.0, 0.0, 0.15), pixels=64, eval_pixels=256, clock="realtime", clock_cost_s=1.5,
        starts=StartConfig(source="truth-offset", count=6, min_deg=15.0, max_deg=20.0, shift_m=0.25),
        optimizer=OptimizerConfig(iterations=6), monte_carlo=MonteCarloConfig(keep=(2, 1), spawn=2))
    return replace(config, **changes)


def test_realtime_run_skips_interpolates_and_resumes_to_the_same_numbers(toy_run, shirt, tmp_path):
    Inversion.create(_config(toy_run, shirt, tmp_path, timestamp="whole")).run()
    whole = RunFolder(tmp_path / "e" / "nerfinv" / "whole")
    rows, steps = whole.rows(), whole.steps()
    assert [s.index for s in steps] == [0, 1, 3, 5]
    assert [(s.clock_start_s, s.clock_end_s) for s in steps] == [(0.0, 9.0), (9.0, 18.0), (18.0, 27.0), (27.0, 36.0)]
    assert [r.index for r in rows] == [0, 1, 2, 3, 4, 5]
    assert [r.interpolated for r in rows] == [False, False, True, False, True, False]
    assert [r.latency_s for r in rows] == [9.0, 13.0, 17.0, 12.0, 16.0, 11.0]  # estimated_s minus 5 s per frame
    for j in (2, 4):  # halfway in time between the estimates of its neighbours
        expected = interpolated_pose(torch.tensor(rows[j - 1].c2w_model), torch.tensor(rows[j + 1].c2w_model), 0.5)
        np.testing.assert_allclose(rows[j].c2w_model, expected.numpy(), atol=1e-9)
        assert rows[j].rotation_deg is not None and rows[j].loss is None and rows[j].steps == 0
    summary = whole.summary()
    assert summary.clock == "realtime" and summary.frames_skipped == 2 and summary.complete
    assert summary.latency_s.mean == pytest.approx(45.0 / 4) and summary.estimated_only.frames == 4
    with open(whole.path / "results.csv", newline="") as handle:  # the CSV carries the clock's columns too
        table = list(csv.DictReader(handle))
    assert [row["interpolated"] for row in table] == ["False", "False", "True", "False", "True", "False"]
    assert [float(row["latency_s"]) for row in table] == [9.0, 13.0, 17.0, 12.0, 16.0, 11.0]
    assert [float(row["estimated_s"]) - float(row["observed_s"]) for row in table] == [9.0, 13.0, 17.0, 12.0, 16.0,
                                                                                      11.0]

    def stop_in_third_step(i: int, record: IterationRecord) -> None:
        if len(RunFolder(tmp_path / "e" / "nerfinv" / "cut").steps()) == 2 and i == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        Inversion.create(_config(toy_run, shirt, tmp_path, timestamp="cut"), Events(iteration=stop_in_third_step)).run()
    cut = tmp_path / "e" / "nerfinv" / "cut"
    assert [r.index for r in RunFolder(cut).rows()] == [0, 1]
    Inversion.resume(cut).run()
    assert [s.index for s in RunFolder(cut).steps()] == [0, 1, 3, 5]
    for a, b in zip(rows, RunFolder(cut).rows(), strict=True):
        for key in ("index", "interpolated", "c2w_model", "loss", "rotation_deg", "observed_s", "estimated_s",
                    "latency_s"):
            assert getattr(a, key) == getattr(b, key), (key, getattr(a, key), getattr(b, key))

    page = write_report(whole.path, overlays=False)
    assert (whole.path / "report" / "latency_vs_time.png").is_file()
    html = page.read_text()
    assert "Latency (observation to estimate)" in html and "interpolated" in html


def test_realtime_clock_without_timestamps_is_refused_before_anything_is_written(toy_run, tmp_path):
    config = _config(toy_run, Path("."), tmp_path, sequence=f"{toy_run[1]}:test", starts=StartConfig(
        source="truth-offset", count=2))
    with pytest.raises(InversionError, match="--frame-interval-s"):
        Inversion.create(config).run()
    assert not (tmp_path / "e").exists()
