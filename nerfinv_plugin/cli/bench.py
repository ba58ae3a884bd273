"""``ns-invert-bench``: nerfinv's benchmarks, one subcommand each, as ``ns-render`` does it.

``grid`` runs experiment grids of ``ns-invert`` runs; ``perf``, ``render``, ``screw`` and ``bank`` measure one
trained model and share its options (:class:`ModelBench`); ``viewer`` times ``ns-invert`` with and without a
watched viewer, and ``lightbox`` compares the lightbox-like domain with the synthetic one. The measuring lives
in ``nerfinv_plugin.bench``; this module parses, calls and prints the tables (markdown, to paste into
docs/benchmarks.md).
"""

import dataclasses
import json
import os
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from tyro.conf import Positional, UseAppendAction, arg

from nerfinv_plugin.bench.gpu_check import GpuCheck, gpu_check
from nerfinv_plugin.bench.grid import (
    Bench,
    Cell,
    CellRunner,
    Grid,
    GridError,
    GridEvents,
    in_process,
    merge,
    parse_overrides,
    read_grid,
    with_cases,
)
from nerfinv_plugin.bench.lightbox import by_trajectory, domain_gaps
from nerfinv_plugin.bench.observed import read_observed
from nerfinv_plugin.bench.perf import MB, compare_loops, latency_rows, latency_runs, model_header, profile_ours, sweep
from nerfinv_plugin.bench.ray_runner import RayRunner
from nerfinv_plugin.bench.recall import bank_benchmark
from nerfinv_plugin.bench.render_speed import render_problem, render_speed
from nerfinv_plugin.bench.sampling import Sampling
from nerfinv_plugin.bench.scoring import SUCCESS_DEG, aggregate, under_key
from nerfinv_plugin.bench.screw import screw_runs, summarize
from nerfinv_plugin.bench.tables import TABLE_MD
from nerfinv_plugin.bench.viewer_overhead import BrowserPriority, OverheadPair, viewer_overhead
from nerfinv_plugin.cli import Interrupted, run
from nerfinv_plugin.data.sequences import SequenceError
from nerfinv_plugin.initialization.bank import BankConfig
from nerfinv_plugin.inversion.session import Events, InversionError
from nerfinv_plugin.inversion.settings import InvertConfig, RenderConfig, SettingsError, preset_path, read_yaml, updated
from nerfinv_plugin.inversion.validation import check, number, several, validate, whole
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.loading import Device, ModelLoadError, load_model
from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.synth.scenes import SceneName
from nerfinv_plugin.synth.trajectories import TrajectoryKind
from nerfinv_plugin.viewer.browser import BrowserError


@dataclass
class GridBench:
    """Run an experiment grid (cases x variants x seeds) of ns-invert runs and tabulate its successes.

    Every case of the grid file runs under every variant and seed (one ns-invert run each), skipping the
    runs already finished and continuing interrupted ones; grid.csv, table.md, grid.json and figures go
    into <out>/<grid name>/. Run the same command again to continue a stopped grid. See docs/bench.md and
    the grids in configs/bench/."""

    grid: Annotated[Path, Positional, arg(metavar="GRID_YML")]
    """Grid file (YAML): base preset and overrides, cases (model config.yml and sequence), variants and
    seeds. Paths in it are relative to the current directory."""
    out: Path = Path("outputs")
    """Results root: the grid writes <out>/<grid name>/ (its runs in nerfinv/<case>-<variant>-s<seed>/)."""
    case: Annotated[tuple[tuple[str, str, str], ...], UseAppendAction, arg(metavar="LABEL CONFIG_YML SEQUENCE")] = ()
    """Run these cases instead of the grid file's: LABEL CONFIG_YML SEQUENCE, repeated. A LABEL of the
    grid file keeps that case's overrides (target, resolution, frames); only its paths change."""
    seeds: tuple[int, ...] | None = None
    """Seeds to run instead of the grid file's (the thesis ran each case 10 times: 0 1 2 3 4 5 6 7 8 9)."""
    preset: str | None = None
    """Base preset instead of the grid file's (a name in configs/ or a YAML file)."""
    override: tuple[str, ...] = ()
    """Base settings KEY=VALUE on top of the grid file's, for every cell, with dotted keys and YAML values:
    device=cuda stop=5 monte_carlo.keep=[5,5]."""
    ray: Annotated[tuple[str, ...] | None, arg(metavar="[ADDRESS]")] = None
    """Run the cells side by side as Ray tasks: --ray alone starts a local Ray for this run (this machine's
    CPUs), --ray ADDRESS joins an existing cluster (ray.init's address: auto, HOST:PORT, ray://HOST:10001).
    Needs pip install 'nerfinv[ray]'. Unset: one cell after the other in this process."""
    ray_cpus: int = 1
    """With --ray: CPUs each cell asks for; torch in the cell uses as many threads."""
    ray_gpus: float = 0.25
    """With --ray: share of a GPU each cell asks for when the cluster has GPUs and the cell's device is not
    cpu (0.25: four cells per GPU)."""
    ray_retries: int = 3
    """With --ray: times Ray runs a cell again whose worker process died (a cell that raises is recorded as
    failed, not retried)."""
    ray_shared_storage: bool = False
    """With --ray: every node sees the grid's paths (models, sequences, --out) at the same place and can run
    in this directory, so cells open and write them there; otherwise the models and sequences are sent
    through Ray's object store and each cell's results come back to this machine."""

    def load(self) -> Grid:
        """The grid file with this command line's replacements."""
        grid = read_grid(self.grid)
        if self.case:
            grid = with_cases(grid, self.case)
        changes = {"overrides": merge(grid.overrides, parse_overrides(self.override, "--override"))}
        if self.seeds is not None:
            changes["seeds"] = list(self.seeds)
        if self.preset is not None:
            changes["preset"] = self.preset
        return dataclasses.replace(grid, **changes)

    def runner(self) -> CellRunner:
        """Where the cells run: here, or on Ray."""
        ray_options = (self.ray_cpus, self.ray_gpus, self.ray_retries, self.ray_shared_storage)
        if self.ray is None:
            if ray_options != (1, 0.25, 3, False):
                raise GridError("--ray-cpus, --ray-gpus, --ray-retries and --ray-shared-storage apply to --ray; "
                                "add --ray (a local Ray) or --ray ADDRESS")
            return in_process
        if len(self.ray) > 1:
            raise GridError(f"--ray takes at most one address, not {' '.join(self.ray)}")
        return RayRunner(self.ray[0] if self.ray else None, *ray_options)

    def main(self) -> None:
        bench_grid(self.load(), self.out, Console(soft_wrap=True), self.runner())  # a cell's error on one line


def _cell_line(record: dict) -> str:
    if record["status"] == "failed":
        return f"[red]{record['cell']}: failed: {escape(record['error'])}[/red]"
    return (f"{record['cell']}: final rotation error {record['final_rotation_deg']:.2f} deg, translation "
            f"{record['final_translation_m']:.3f} m, {record['frames']} frames in {record['wall_time_s']:.0f} s")


def _variant_line(group: dict) -> str:
    counts = ", ".join(f"{group['successes'][under_key(t)]}/{group['done']} < {t:g} deg" for t in SUCCESS_DEG)
    pending = group["cells"] - group["done"] - group["failed"]
    return f"{group['variant']}: {counts} ({group['failed']} failed, {pending} to run)"


def bench_grid(grid: Grid, out: Path, console: Console, runner: CellRunner = in_process) -> list[dict]:
    """Run with a progress display: cells done of all, and the steps of the cell running here."""
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        cells = progress.add_task("cells done", total=None)
        steps = progress.add_task("", total=None, visible=False)

        def begin(records: list[dict]) -> None:
            progress.update(cells, total=len(records), completed=sum(r["status"] == "done" for r in records))

        def cell_start(cell: Cell, resumed: bool) -> None:
            progress.update(steps, description=f"{cell.label} ({'resumed' if resumed else 'new'}): steps",
                            completed=0, total=None, visible=True)

        def cell_end(record: dict) -> None:
            console.print(_cell_line(record))
            progress.update(steps, visible=False)
            progress.advance(cells)

        def inversion(cell: Cell) -> Events:
            return Events(begin=lambda total, done, iterations: progress.update(steps, total=total, completed=done),
                          step=lambda row: progress.advance(steps),
                          warn=lambda message: console.print(f"[yellow]{cell.label}: {escape(message)}[/yellow]"))

        bench = Bench(grid, out, GridEvents(begin, cell_start, cell_end, inversion, info=console.print), runner)
        console.print(f"grid {grid.name}: {len(bench.cells)} cells into {bench.folder}")
        try:
            records = bench.run()
        except KeyboardInterrupt:
            sent = isinstance(runner, RayRunner) and not runner.shared_storage
            running = "cells that were running on Ray start again" if sent else \
                "the cells that were running resume where they stopped"
            raise Interrupted(f"interrupted; the finished cells are in {bench.folder / TABLE_MD}. Run the same "
                              f"command again to continue ({running})") from None
    for group in aggregate(records, by_case=False):
        console.print(f"[bold]{_variant_line(group)}[/bold]")
    console.print(f"table: {bench.folder / TABLE_MD}")
    return records


@dataclass(kw_only=True)
class ModelBench:
    """Options of every benchmark that measures one trained model."""

    load_config: Path
    """config.yml of a trained run."""
    device: Device = "auto"
    """Where to render."""
    threads: int | None = None
    """CPU threads torch may use (timings depend on it). Unset: torch's own choice."""

    def load(self) -> LoadedModel:
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        return load_model(self.load_config, device=self.device)

    def header(self, loaded: LoadedModel) -> str:
        """What a measured table needs next to it: the model, the machine's settings and the date."""
        return model_header(loaded, self.load_config)


@dataclass(kw_only=True)
class SpeedBench(ModelBench):
    """Options of the two throughput benchmarks, the thesis' way against ours."""

    candidates: int = 15
    """Candidates per iteration (the thesis: 15)."""
    pixels: int = 256
    """Pixels per candidate and iteration."""
    seed: int = 0
    """Seeds the candidate poses and the pixels."""
    render: Sampling = field(default_factory=Sampling)
    """How our side samples rays (as ns-invert's --render options); the thesis' side renders as trained."""


@dataclass(kw_only=True)
class PerfBench(SpeedBench):
    """Time one Monte Carlo step on one frame the thesis' way and ours (or how ours scales, or profile it).

    N candidates x P pixels x iterations in this process, the thesis' loop in two parts with our step timed
    before, between and after them (the median of those three counts): time per iteration, rays per second,
    peak memory and the ratio. With --sweep, time ours over candidate and pixel counts;
    with --profile, where our time goes."""

    sequence: str
    """A sequence with ground truth (ns-invert's --sequence); the starts are placed around its frame."""
    candidates: int | None = None
    """Candidates per iteration. Unset: 15 (the thesis); with --latency, ns-invert's (or --preset's) starts."""
    pixels: int | None = None
    """Pixels per candidate and iteration. Unset: 256 (the thesis); with --latency, ns-invert's (or
    --preset's)."""
    frame: int = 0
    """Which frame of the sequence to invert."""
    resolution: tuple[int, int] | None = None
    """Working resolution WIDTH HEIGHT (default: the images' own)."""
    iterations: int | None = None
    """Iterations per step. Unset: 60 (the thesis); with --latency, ns-invert's (or --preset's)."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Target centre in the dataset frame."""
    sweep: bool = False
    """Time ours for 1 to 80 candidates and 64 to 4096 pixels (sweep-iterations each) instead."""
    sweep_iterations: int = 5
    """Iterations per point of the sweep."""
    profile: bool = False
    """Profile 5 of our iterations with torch.profiler instead and print the operators that take the most
    CPU time."""
    latency: bool = False
    """Run ns-invert --clock realtime over the sequence instead (a SHIRT trajectory: its frames 5 s apart),
    with the compute time measured, at each --clock-speeds, --latency-runs times: latency per frame, frames
    skipped, time to first lock, accuracy (medians over the runs). The inversion is ns-invert's (or
    --preset's), with --candidates as --starts.count, --pixels and --iterations where given, and --seed,
    --resolution, --target, --device, --start and --stop; our --render options do not apply (ns-invert's own
    do)."""
    clock_speeds: tuple[float, ...] = (1.0, 0.1)
    """--latency: the clock speeds to run at (0.1: a computer ten times slower)."""
    latency_runs: int = 3
    """--latency: runs at each speed."""
    preset: str | None = None
    """--latency: ns-invert preset to start from (a name in configs/ or a YAML file)."""
    start: int = 0
    """--latency: first frame of the sequence."""
    stop: int | None = None
    """--latency: frame to stop before. Default: the end of the sequence."""
    out: Path = Path("outputs")
    """--latency: the runs go to <out>/latency/nerfinv/<time>-speed<S>-run<i>/."""

    def main(self) -> None:
        console = Console(soft_wrap=True)  # table rows on one line, to paste
        if self.latency:
            self.latency_main(console)
            return
        candidates, pixels, iterations = self.candidates or 15, self.pixels or 256, self.iterations or 60  # the thesis'
        loaded = self.load()
        observed = read_observed(loaded, self.sequence, self.frame, self.target, self.resolution)
        width, height = observed.intrinsics.width, observed.intrinsics.height
        console.print(f"{self.header(loaded)}; frame {observed.name} at {width}x{height}")
        if self.sweep:
            points = [(n, pixels) for n in (1, 5, 15, 40, 80)] + [(candidates, p) for p in (64, 1024, 4096)]
            swept = sweep(loaded, observed, points, self.sweep_iterations, self.render, self.seed)
            console.print(f"chunk {swept.chunk_rays} rays, memory budget {swept.memory_budget_bytes / MB:,.0f} MB")
            console.print("| candidates | pixels | rays / iteration | s / iteration | us / ray | peak memory |\n"
                          "|---|---|---|---|---|---|")
            for point in swept.points:
                t, rays = point.timing, point.candidates * point.pixels
                console.print(f"| {point.candidates} | {point.pixels} | {rays:,} | {t.per_iteration:.3f} | "
                              f"{1e6 * t.per_iteration / rays:.1f} | {t.peak_memory_bytes / MB:,.0f} MB |")
            return
        if self.profile:
            found = profile_ours(loaded, observed, candidates, pixels, self.render, seed=self.seed)
            console.print(f"{candidates} candidates x {pixels} pixels x {found.iterations} iterations: "
                          f"{found.cpu_s:.2f} s of CPU time in operators")
            console.print("| operator | self CPU time | share | calls |\n|---|---|---|---|")
            for op in found.operators:
                console.print(f"| {op.name} | {op.self_cpu_s:.3f} s | {100 * op.self_cpu_s / found.cpu_s:.1f}% | "
                              f"{op.calls} |")
            return
        compared = compare_loops(loaded, observed, candidates, pixels, iterations, self.render, self.seed)
        console.print(f"{candidates} candidates x {pixels} pixels x {iterations} iterations")
        console.print("| way | s / iteration | rays / s (fwd+bwd) | peak memory | first loss (mean) |\n"
                      "|---|---|---|---|---|")
        for name, t in (("thesis (per-candidate patched get_outputs_for_camera_ray_bundle, trainable weights, "
                         "keypoints every iteration)", compared.thesis), ("nerfinv (ns-invert's step)", compared.ours)):
            console.print(f"| {name} | {t.per_iteration:.3f} | {t.rays_per_second:,.0f} | "
                          f"{t.peak_memory_bytes / MB:,.0f} MB | {float(np.mean(t.first_losses)):.4f} |")
        runs = ", ".join(f"{t.per_iteration:.3f}" for t in compared.ours_runs)
        console.print(f"ours, s / iteration, before the thesis' loop and after each of its parts: {runs} (the "
                      "median in the table)")
        console.print(f"ratio (thesis time per iteration / ours): [bold]{compared.ratio:.2f}x[/bold]")

    def latency_config(self) -> InvertConfig:
        """The ns-invert settings of the latency runs."""
        base = InvertConfig() if self.preset is None else \
            updated(InvertConfig(), read_yaml(preset_path(self.preset)), self.preset)
        config = dataclasses.replace(
            base, load_config=self.load_config, sequence=self.sequence, output_dir=self.out, name="latency",
            device=self.device, seed=self.seed, target=self.target, start=self.start, stop=self.stop,
            resolution=self.resolution if self.resolution is not None else base.resolution,
            pixels=self.pixels or base.pixels,
            starts=dataclasses.replace(base.starts, count=self.candidates or base.starts.count),
            optimizer=dataclasses.replace(base.optimizer, iterations=self.iterations or base.optimizer.iterations),
            preset=self.preset)
        validate(config)
        return config

    def latency_main(self, console: Console) -> None:
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        config = self.latency_config()
        load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
        console.print(f"ns-invert --clock realtime on {self.sequence} (frames {self.start}:{self.stop or ''}), "
                      f"{config.starts.count} starts, {config.pixels} pixels x {config.optimizer.iterations} "
                      "iterations, "
                      f"{torch.get_num_threads()} torch threads, load average {load} before, "
                      f"{datetime.now():%Y-%m-%d %H:%M}")

        def events(speed: float, repeat: int) -> Events:
            return Events(frame=lambda row: console.print(
                f"speed {speed:g} run {repeat}: frame {row.frame} "
                f"{'interpolated' if row.interpolated else 'estimated'}, latency {row.latency_s:.1f} s"
                + ("" if row.rotation_deg is None else f", {row.rotation_deg:.1f} deg")))

        try:
            runs = latency_runs(config, self.clock_speeds, self.latency_runs, events)
        except KeyboardInterrupt:
            raise Interrupted(f"interrupted; the finished runs are in {self.out / 'latency' / 'nerfinv'}") from None
        for run_ in runs:
            console.print(f"run: {run_.run}")
        console.print(f"load average after: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
        console.print("| clock speed | runs | frames | mean latency (s) | max latency (s) | frames skipped | "
                      "first lock (s, runs locked) | rotation mean, all frames (deg) | estimated alone (deg) | "
                      "under 5 deg |\n"
                      "|---|---|---|---|---|---|---|---|---|---|")
        for row in latency_rows(runs):
            lock = "never" if row.time_to_first_lock_s is None else f"{row.time_to_first_lock_s:.1f}"
            rot = "–" if row.rotation_mean_deg is None else f"{row.rotation_mean_deg:.2f}"
            est = "–" if row.rotation_mean_estimated_deg is None else f"{row.rotation_mean_estimated_deg:.2f}"
            under = "–" if row.under_5deg is None else f"{100 * row.under_5deg:.0f}%"
            console.print(f"| {row.clock_speed:g} | {row.runs} | {row.frames} | {row.mean_latency_s:.2f} | "
                          f"{row.max_latency_s:.2f} | {row.frames_skipped:g} | {lock} ({row.locked_runs}/{row.runs}) | "
                          f"{rot} | {est} | {under} |")


@dataclass(kw_only=True)
class GpuBench(SpeedBench):
    """On a machine with CUDA: check the CUDA path against the CPU one, then fill a GPU row of the throughput
    tables. The same checkpoint is loaded on both devices; the same candidates (5-15 degrees off the frame's
    truth) render the same random pixels on each, and the colours, accumulations and pose gradients must agree
    (1e-3 on colours, 1% of the largest gradient entry); exit code 1 when they do not. Then ns-invert-bench
    perf's comparison runs on the GPU, and the default view bank is rendered there, forward only. Never part
    of the tests: they run without a GPU."""

    sequence: str
    """A sequence with ground truth (ns-invert's --sequence); the candidates are placed around its frame."""
    frame: int = 0
    """Which frame of the sequence to use."""
    resolution: tuple[int, int] | None = None
    """Working resolution WIDTH HEIGHT (default: the images' own)."""
    iterations: int = 60
    """Iterations of the throughput comparison (the thesis: 60)."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Target centre in the dataset frame."""

    def main(self) -> None:
        if not torch.cuda.is_available():
            raise ModelLoadError("no CUDA device here (torch.cuda.is_available() is False): run ns-invert-bench gpu "
                                 "on a machine with one")
        console = Console(soft_wrap=True)
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        check = GpuCheck(self.load_config, self.sequence, self.frame, self.resolution, self.target, self.candidates,
                         self.pixels, self.iterations, self.seed, self.render)
        if not gpu_check(check, console):
            raise SystemExit(1)


@dataclass(kw_only=True)
class RenderBench(SpeedBench):
    """Time one inversion iteration (render, loss, backward) the thesis' way and ours, on the same rays.

    N candidates at P pixels, alternately in one process: rays per second of each way and the ratio, and
    how far apart the two ways' colours are."""

    repeats: int = 5
    """Timed iterations of each way (after one warm-up each); the median is reported."""
    range_m: float = 5.0
    """Distance of the candidate cameras (random, looking at the dataset origin) in dataset units."""
    width: int = 240
    """Image width in pixels; the field of view is SPEED+'s."""
    height: int = 150
    """Image height in pixels."""
    on_target: bool = False
    """Draw the pixels only where the first candidate's rays cross the target sphere (as interest-region
    pixels on the object are), instead of anywhere in the image, where many rays miss it and cost ours
    nothing."""

    def main(self) -> None:
        console = Console(soft_wrap=True)  # table rows on one line, to paste
        loaded = self.load()
        problem = render_problem(loaded, self.candidates, self.pixels, self.range_m, self.width, self.height,
                                 self.render, self.on_target, self.seed)
        speed = render_speed(loaded, problem, self.render, self.repeats)
        r = self.render
        console.print(f"{self.header(loaded)}; {self.candidates} candidates x {self.pixels} pixels = {speed.rays} "
                      f"rays, chunk {speed.chunk_rays} rays; ours: target radius {r.target_radius_m}, samples "
                      f"{r.proposal_samples} / {r.nerf_samples}; colour difference between the ways: mean "
                      f"{speed.colour_diff_mean:.2e}, max {speed.colour_diff_max:.2e}")
        console.print("| way | s / iteration (median) | rays / s (fwd+bwd) |\n|---|---|---|")
        console.print("| thesis: per-candidate get_outputs_for_camera_ray_bundle, stock hash forward, weights "
                      f"trainable | {speed.thesis_median_s:.3f} | {speed.rays / speed.thesis_median_s:,.0f} |")
        console.print("| nerfinv: one batched bundle, chunked, fused hash forward, frozen weights, bounded rays | "
                      f"{speed.ours_median_s:.3f} | {speed.rays / speed.ours_median_s:,.0f} |")
        console.print(f"ratio (thesis time / ours): [bold]{speed.ratio:.2f}x[/bold]")


@dataclass(kw_only=True)
class ScrewBench(ModelBench):
    """Optimize the same starts on one frame with screws about the target and about the world origin.

    Prints each parameterisation's final errors (median over the seeds) and time per step."""

    sequence: str
    """A sequence of the same object with ground truth: a SHIRT trajectory (<root>/roeN[/domain]), a Blender
    split (<scene>:<split>) or an image folder with camera.json and poses.json."""
    frame: int = 0
    """Which frame to invert."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Target centre in the dataset frame: what the screws turn about, and the starts."""
    candidates: int = 8
    """Candidates optimized together."""
    iterations: int = 60
    """Iterations of the one Monte Carlo step."""
    min_deg: float = 15.0
    """Starts are turned by at least this angle about the target..."""
    max_deg: float = 20.0
    """...and at most this one."""
    shift_fraction: float = 0.05
    """...and moved by this fraction of the true range."""
    seeds: int = 3
    """Repetitions with different starts and pixels: seeds seed, seed + 1, ..."""
    seed: int = 0
    """The first seed."""

    def main(self) -> None:
        console = Console(soft_wrap=True)  # table rows on one line, to paste
        loaded = self.load()
        observed = read_observed(loaded, self.sequence, self.frame, self.target)
        runs = screw_runs(loaded, observed, self.candidates, self.iterations, self.min_deg, self.max_deg,
                          self.shift_fraction, range(self.seed, self.seed + self.seeds))
        console.print(f"{self.header(loaded)}; {self.sequence} frame {self.frame}, {self.candidates} candidates, "
                      f"{self.iterations} iterations, starts {self.min_deg:g}-{self.max_deg:g} deg and "
                      f"{self.shift_fraction:.0%} of the range off, {self.seeds} seeds")
        console.print("| screw about | best error, deg (median over seeds) | all candidates' median error, deg "
                      "| s per step |\n|---|---|---|---|")
        for row in summarize(runs):
            console.print(f"| {row.origin} | {row.best_deg:.2f} | {row.median_deg:.2f} | {row.seconds:.1f} |")


@dataclass(kw_only=True)
class BankBench(ModelBench):
    """Build (or read) the view bank as ns-invert does, then score its recall on sequences with truth.

    Every frame with ground truth and the object wholly in view is matched; prints the share whose first
    hypothesis, and whose first --hypotheses, include one within --threshold-deg of the true attitude,
    and the build and match times."""

    sequences: tuple[str, ...]
    """Sequences with ground truth (ns-invert's --sequence forms: SHIRT root/roeN, scene:split, folders)."""
    resolution: tuple[int, int] | None = None
    """Working resolution WIDTH HEIGHT (default: the images' own)."""
    hypotheses: int = 20
    """Hypotheses per frame that count for recall."""
    threshold_deg: float = 15.0
    """A hypothesis this close to the true attitude is a hit."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Target centre in the dataset frame (metres)."""
    rebuild: bool = False
    """Render the bank even when a cached one exists (to time the build; rays must be bounded)."""
    bank: BankConfig = field(default_factory=BankConfig)
    render: RenderConfig = field(default_factory=RenderConfig)

    def main(self) -> None:
        console = Console(soft_wrap=True)  # table rows on one line, to paste
        loaded = self.load()
        with Progress(console=console) as progress:
            def on_build(views: int):
                task = progress.add_task("view bank", total=views)
                return lambda done: progress.update(task, advance=done)

            result = bank_benchmark(loaded, self.sequences, self.target, self.bank, self.render, self.hypotheses,
                                    self.threshold_deg, self.resolution, self.rebuild, on_build)
        radius = "not bounded" if result.radius_m is None else \
            f"{result.radius_m:.3f} m ({'given' if result.radius_given else 'measured'}, {result.bound_s:.1f} s)"
        source = f"rendered in {result.build_s:.1f} s" if result.built else \
            f"read from the cache (rendered in {result.build_s:.1f} s when built)"
        console.print(f"{self.header(loaded)}; object radius {radius}; bank {self.bank.views} views x "
                      f"{self.bank.in_plane} angles at {self.bank.render_px} px: {source}, ready in "
                      f"{result.ready_s:.1f} s ({result.entries} entries)")
        console.print(f"| sequence | frames | left out | top-1 within {self.threshold_deg:g} deg | "
                      f"top-{self.hypotheses} | median best error (deg) | median range error (top-1) | "
                      "match s (median, max) |\n|---|---|---|---|---|---|---|---|")
        for recall in result.recalls:
            times = recall.match_s or [float("nan")]
            console.print(f"| {recall.name} | {recall.frames} | {recall.skipped} | {100 * recall.top1:.0f}% | "
                          f"{100 * recall.topk:.0f}% | {recall.median_best_deg:.1f} | "
                          f"{100 * recall.median_range_error:.1f}% | {np.median(times):.3f}, {max(times):.3f} |")
        if result.frames:
            top1, topk = result.overall()
            console.print(f"[bold]all {result.frames} frames: top-1 {100 * top1:.1f}%, "
                          f"top-{self.hypotheses} {100 * topk:.1f}%[/bold]")


VIEWER_RULES = {"target": several(number(), 3), "stop": whole(1), "repeats": whole(1), "iterations": whole(1)}
"""What the numeric options of ``viewer`` accept (nerfinv_plugin/inversion/validation.py)."""


@dataclass(kw_only=True)
class ViewerBench:
    """Time ns-invert without the viewer and with it (--no-viewer-render) while one headless Chromium watches.

    The two runs alternate --repeats times so that a change in the machine's load falls on both; prints
    each pair's inversion wall time and this process's CPU time (the viewer's own work) of both runs and the
    browser's CPU time, then the medians and their ratios. The runs go to a temporary folder. Needs
    selenium (pip install 'nerfinv[test]') and chromium with chromium-driver (apt-get)."""

    load_config: Path
    """config.yml of a trained run."""
    sequence: str
    """The observed sequence with ground truth (ns-invert's --sequence); the starts are turned off the truth."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Target centre in the dataset frame."""
    stop: int = 4
    """Frames inverted per run."""
    repeats: int = 3
    """Pairs of runs (without, with the viewer)."""
    iterations: int = 30
    """Iterations per Monte Carlo step."""
    browser_priority: BrowserPriority = "normal"
    """normal: the browser shares the cores with the run as any program does (here it draws viser's canvas in
    software, which takes about a core); idle: once connected it runs only on time the run leaves (Linux
    SCHED_IDLE), standing in for a browser on another machine or a GPU."""

    def main(self) -> None:
        check(self, VIEWER_RULES)
        console = Console(soft_wrap=True)  # table rows on one line, to paste
        load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
        console.print(f"ns-invert on {self.sequence} (frames 0:{self.stop}) with {self.load_config}, "
                      f"{self.iterations} iterations, load average {load} before, {datetime.now():%Y-%m-%d %H:%M}")

        def on_pair(pair: OverheadPair) -> None:
            console.print(f"pair: without viewer {pair.wall_off_s:.2f} s (CPU {pair.cpu_off_s:.2f} s), viewer, one "
                          f"browser {pair.wall_on_s:.2f} s (CPU {pair.cpu_on_s:.2f} s); the browser's CPU "
                          f"{pair.browser_cpu_s:.2f} s")

        try:
            with console.status("runs without and with the viewer"):
                measured = viewer_overhead(self.load_config, self.sequence, self.target, self.stop, self.iterations,
                                           self.repeats, on_pair, self.browser_priority)
        except KeyboardInterrupt:
            raise Interrupted("interrupted; the pairs printed above are finished") from None
        for name, wall in (("inversion wall time", True), ("process CPU time", False)):
            off, on = measured.medians(wall)
            console.print(f"{name}: median without viewer {off:.2f} s, with the viewer and one browser {on:.2f} s, "
                          f"ratio {on / off:.3f}")


LIGHTBOX_RULES = {"seed": whole(0), "spp": whole(1), "num-frames": whole(1), "width": whole(1), "height": whole(1)}
"""What the numeric options of ``lightbox`` accept (nerfinv_plugin/inversion/validation.py)."""


@dataclass(kw_only=True)
class LightboxBench:
    """Render SHIRT trajectories of a scene in the synthetic and the lightbox-like domain and compare them.

    The default trajectories, undistorted, go into <out>/shirt as ns-invert-synth --trajectory.lightbox
    writes them; prints per frame the PSNR of the lightbox image against the synthetic one and the IoU of
    the object mask found on the lightbox image (find_object) with the object's alpha and with the mask
    found on a clean render of the lab lighting, then each trajectory's medians. Writes the numbers to
    <out>/lightbox-gap.json."""

    out: Path
    """Output folder."""
    scene: SceneName = "tango"
    """tango: the spacecraft; toy: the tabletop object; satellite: the satellite with thin parts."""
    seed: int = 0
    """The generator's seed (textures, attitudes, render and camera noise)."""
    spp: int = 64
    """Samples per pixel of every render."""
    kinds: tuple[TrajectoryKind, ...] = ("roe1", "roe2")
    """Trajectories to render."""
    num_frames: int = 20
    """Frames per trajectory."""
    width: int = 240
    """Image width in pixels."""
    height: int = 150
    """Image height in pixels."""

    def main(self) -> None:
        check(self, LIGHTBOX_RULES)
        console = Console(soft_wrap=True)  # one line a frame, however narrow the terminal
        with console.status(f"rendering {self.scene} in both domains"):
            gaps = domain_gaps(self.out, self.scene, self.kinds, self.num_frames, self.width, self.height,
                               self.seed, self.spp)
        for gap in gaps:
            console.print(f"{gap.trajectory}/{gap.filename}: PSNR {gap.psnr_db:.2f} dB; mask IoU with alpha "
                          f"{gap.iou_alpha:.3f}, with the clean render's mask {gap.iou_clean:.3f} (clean render "
                          f"with alpha {gap.clean_iou_alpha:.3f}, synthetic image with alpha "
                          f"{gap.synthetic_iou_alpha:.3f})")
        for t in by_trajectory(gaps):
            console.print(f"{t.trajectory}: PSNR median {t.psnr_median_db:.2f} dB; IoU with alpha median "
                          f"{t.iou_alpha_median:.3f} (min {t.iou_alpha_min:.3f}); with the clean render's mask "
                          f"median {t.iou_clean_median:.3f} (min {t.iou_clean_min:.3f})")
        write_atomic(self.out / "lightbox-gap.json",
                     json.dumps({"settings": dataclasses.asdict(self), "frames": [dataclasses.asdict(g) for g in gaps]},
                                indent=2, default=str))


Commands = (
    Annotated[GridBench, tyro.conf.subcommand(name="grid", description="experiment grids of ns-invert runs: "
                                              "success counts, tables, plots")]
    | Annotated[PerfBench, tyro.conf.subcommand(name="perf", description="one Monte Carlo step, the thesis' "
                                                "way and ours: time, rays/s, memory; --sweep, --profile")]
    | Annotated[GpuBench, tyro.conf.subcommand(name="gpu", description="on a CUDA machine: its renders and "
                                               "gradients against the CPU's, then a GPU row of the perf table")]
    | Annotated[RenderBench, tyro.conf.subcommand(name="render", description="one iteration's render + "
                                                  "backward, the thesis' way and ours, on the same rays")]
    | Annotated[ScrewBench, tyro.conf.subcommand(name="screw", description="screws about the target against "
                                                 "the thesis' world origin, from the same starts")]
    | Annotated[BankBench, tyro.conf.subcommand(name="bank", description="the view bank: build and match time, "
                                                "recall of its hypotheses")]
    | Annotated[ViewerBench, tyro.conf.subcommand(name="viewer", description="ns-invert with and without the "
                                                  "viewer and one headless browser watching: time, CPU")]
    | Annotated[LightboxBench, tyro.conf.subcommand(name="lightbox", description="the lightbox-like domain "
                                                    "against the synthetic one: PSNR and mask IoU per frame")]
)
"""``ns-invert-bench SUBCOMMAND [OPTIONS]``: a subcommand is required (``--help`` lists them)."""


def entrypoint() -> None:
    run(Commands, "ns-invert-bench", GridError, SettingsError, ModelLoadError, SequenceError, InversionError,
        BrowserError, default=tyro.MISSING_NONPROP)  # no default: a subcommand is required


if __name__ == "__main__":
    entrypoint()
