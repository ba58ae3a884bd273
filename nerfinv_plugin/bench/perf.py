"""Inversion throughput, measured the same way for the thesis' implementation and for ours.

The thesis' loop (its section 4.3): every iteration detects keypoints in the observed image, draws the
pixels, renders each candidate through the patched ``get_outputs_for_camera_ray_bundle`` with the
model's weights trainable, stacks the losses, back-propagates once and steps Adam on screw parameters
about the world origin. Ours is :func:`optimize_candidates` with the settings ``ns-invert`` runs with.
Both see the same model, frame, starting poses and pixels (the same random generator draws them, so
the first iteration renders the same rays both ways), and the model comes back from either as it went in.

The latency mode (:func:`latency_runs`) runs ``ns-invert --clock realtime`` itself over a trajectory with
its timestamps (SHIRT: 5 s apart) and the compute time measured: latency per frame, frames skipped, time to
first lock and accuracy, the medians over repeated runs (:func:`latency_rows`).
"""

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
import psutil
import torch
from torch import Tensor

from nerfinv_plugin.bench.observed import ObservedFrame
from nerfinv_plugin.bench.sampling import Sampling
from nerfinv_plugin.geometry.se3 import exp_se3
from nerfinv_plugin.inversion.optimizer import IterationRecord, OptimizerConfig, PreparedFrame, optimize_candidates
from nerfinv_plugin.inversion.sampling import PixelSampler
from nerfinv_plugin.inversion.session import Events, Inversion
from nerfinv_plugin.inversion.settings import InvertConfig
from nerfinv_plugin.model.fused_hash import stock_hash_encoding
from nerfinv_plugin.model.gradients import keep_gradients
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import AS_TRAINED, Intrinsics, RenderSettings, memory_budget_bytes, pinhole_cameras
from nerfinv_plugin.results.records import RunSummary

START_MIN_DEG, START_MAX_DEG, START_SHIFT_M = 15.0, 20.0, 0.05
"""Where the throughput benchmarks start: iNeRF's protocol, 15-20 degrees and 5 cm off the truth."""


MB = 1 << 20


def model_header(loaded: LoadedModel, load_config: str | Path) -> str:
    """What a measured table needs next to it: the model, the machine's settings and the date."""
    return (f"model {loaded.config.method_name} step {loaded.step} ({load_config}) on {loaded.device}, "
            f"{torch.get_num_threads()} torch threads, {datetime.now():%Y-%m-%d %H:%M}")


@dataclass(frozen=True)
class Timing:
    seconds: float
    iterations: int
    rays_per_iteration: int
    peak_memory_bytes: int
    """Largest growth of the process' resident memory (CPU) or of allocated CUDA memory during the run."""
    first_losses: np.ndarray
    """[N] the candidates' losses at the first iteration (the starts, before any update): on the same rays
    and with the same render settings, both loops must agree on them."""

    @property
    def per_iteration(self) -> float:
        return self.seconds / self.iterations

    @property
    def rays_per_second(self) -> float:
        return self.rays_per_iteration * self.iterations / self.seconds


@contextmanager
def peak_memory(device: torch.device):
    """Yields a callable returning the peak memory growth since entry: CUDA's allocator statistics, or the
    resident set size sampled every 5 ms on the CPU (the process' own memory, whatever allocated it)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        yield lambda: torch.cuda.max_memory_allocated(device) - base
        return
    process = psutil.Process()
    base = process.memory_info().rss
    peak, stop = [base], threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], process.memory_info().rss)
            time.sleep(0.005)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        yield lambda: peak[0] - base
    finally:
        stop.set()
        thread.join()


def _timed(device: torch.device, work: Callable[[], None]) -> tuple[float, int]:
    """``(seconds, peak memory growth in bytes)`` of ``work()``."""
    with peak_memory(device) as peak:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        tic = time.perf_counter()
        work()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds = time.perf_counter() - tic
    return seconds, int(peak())


@contextmanager
def sampler_as_nerfstudio_loads_it(model: torch.nn.Module):
    """Within the block, nerfacto's proposal sampler has the step count nerfstudio's loader leaves it with (0),
    as the thesis' implementation had it: it then evaluates the proposal networks with autograd recording.
    ``load_model`` gives it the trained step (where it evaluates them under no_grad); it gets it back on exit."""
    sampler = getattr(model, "proposal_sampler", None)
    if sampler is None or not hasattr(sampler, "_step"):
        yield
        return
    saved = sampler._step, sampler._steps_since_update
    sampler._step, sampler._steps_since_update = 0, 0
    try:
        yield
    finally:
        sampler._step, sampler._steps_since_update = saved


def thesis_step(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor, target: Tensor) -> Tensor:
    """One iteration as the thesis' implementation does it: a ray bundle per candidate from nerfstudio's camera,
    rendered through the patched ``get_outputs_for_camera_ray_bundle`` of stock nerfstudio (its own hash-grid
    forward and proposal sampler as its loader leaves them) with the model's weights not frozen, the candidates'
    losses stacked and back-propagated once. ``c2w`` is [N, 3, 4]. Returns the rendered colours [N, P, 3]."""
    model = loaded.model
    rgbs, losses = [], []
    with keep_gradients(model), stock_hash_encoding(model), sampler_as_nerfstudio_loads_it(model):
        for n in range(c2w.shape[0]):
            camera = pinhole_cameras(c2w[n:n + 1], intrinsics).to(loaded.device)
            bundle = camera.generate_rays(camera_indices=0, coords=pixels.float() + 0.5)
            rgb = model.get_outputs_for_camera_ray_bundle(bundle.reshape((pixels.shape[0], 1)))["rgb"][:, 0]
            rgbs.append(rgb)
            losses.append(((rgb - target) ** 2).mean())
    torch.stack(losses).sum().backward()
    return torch.stack(rgbs)


class ThesisLoop:
    """The thesis' implementation, iteration by iteration (see the module docstring), run in parts: its
    candidates and Adam state carry over from one part to the next, so that our step can be timed between
    them (:func:`compare_loops`)."""

    def __init__(self, loaded: LoadedModel, start: Tensor, image: np.ndarray, intrinsics: Intrinsics, pixels: int,
                 lr: float = 0.01, seed: int = 0):
        self.loaded, self.image, self.intrinsics, self.pixels = loaded, image, intrinsics, pixels
        device = loaded.device
        self.observed = torch.as_tensor(image, dtype=torch.float32, device=device) / 255.0
        self.start = start.to(device, torch.float32)
        self.theta = torch.zeros(start.shape[0], 6, device=device, requires_grad=True)
        self.optimizer = torch.optim.Adam([self.theta], lr=lr)
        self.rng = np.random.default_rng(seed)
        self.losses: list[Tensor] = []
        self.seconds, self.iterations, self.peak = 0.0, 0, 0

    def run(self, iterations: int) -> None:
        """``iterations`` more iterations, timed and added to the loop's totals."""
        loaded, device = self.loaded, self.loaded.device

        def work() -> None:
            loaded.model.requires_grad_(True)
            try:
                for _ in range(iterations):
                    chosen = torch.as_tensor(PixelSampler("interest_region", self.pixels).prepare(self.image)
                                             .sample(self.rng), device=device)
                    self.optimizer.zero_grad(set_to_none=True)
                    c2w = (exp_se3(self.theta) @ self.start)[:, :3]
                    target = self.observed[chosen[:, 0], chosen[:, 1]]
                    rgb = thesis_step(loaded, c2w, self.intrinsics, chosen, target)
                    self.losses.append(((rgb.detach() - target) ** 2).mean((1, 2)))
                    self.optimizer.step()
            finally:
                loaded.model.requires_grad_(False)
                loaded.model.zero_grad(set_to_none=True)

        seconds, peak = _timed(device, work)
        self.seconds, self.iterations, self.peak = self.seconds + seconds, self.iterations + iterations, \
            max(self.peak, peak)

    def timing(self) -> Timing:
        return Timing(self.seconds, self.iterations, self.start.shape[0] * self.pixels, self.peak,
                      self.losses[0].cpu().numpy())


def our_loop(loaded: LoadedModel, start: Tensor, image: np.ndarray, intrinsics: Intrinsics, pixels: int,
             centre: Tensor, config: OptimizerConfig, seed: int = 0, settings: RenderSettings = AS_TRAINED) -> Timing:
    """One Monte Carlo step of our engine, rendering under ``settings``: keypoints once, all candidates
    batched, frozen weights. The
    iterations' pixels come from a generator seeded as :class:`ThesisLoop`'s (the ranking pixels from
    another), so both loops draw the same pixels."""
    sampler = PixelSampler("interest_region", pixels).prepare(image)
    eval_pixels = torch.as_tensor(PixelSampler("random", 1024).prepare(image).sample(np.random.default_rng(seed + 1)))
    frame = PreparedFrame.from_image(loaded, image, intrinsics, sampler, eval_pixels, centre)
    history: list[IterationRecord] = []

    def work() -> None:
        history.extend(optimize_candidates(loaded, start, frame, config, np.random.default_rng(seed),
                                           settings=settings).history)

    seconds, peak = _timed(loaded.device, work)
    return Timing(seconds, len(history), start.shape[0] * pixels, peak, history[0].loss)


@dataclass(frozen=True)
class PerfComparison:
    """One Monte Carlo step timed the thesis' way and ours, from the same starts on the same frame."""

    thesis: Timing
    ours_runs: list[Timing]
    """Our step, timed before the thesis' loop and after each of its parts (the same work each time)."""

    @property
    def ours(self) -> Timing:
        """The run with the median time: our step takes seconds where the thesis' loop takes minutes, so one
        run of ours can fall entirely in a burst of load from the machine's other tenants."""
        return sorted(self.ours_runs, key=lambda t: t.seconds)[len(self.ours_runs) // 2]

    @property
    def ratio(self) -> float:
        """Thesis time per iteration over ours: how many times faster ours is."""
        return self.thesis.per_iteration / self.ours.per_iteration


def _starts(loaded: LoadedModel, observed: ObservedFrame, count: int, seed: int) -> Tensor:
    return observed.starts(count, START_MIN_DEG, START_MAX_DEG, START_SHIFT_M * loaded.dataparser_scale, seed)


def compare_loops(loaded: LoadedModel, observed: ObservedFrame, candidates: int, pixels: int, iterations: int,
                  sampling: Sampling, seed: int = 0, parts: int = 2) -> PerfComparison:
    """Time ``iterations`` iterations of ``candidates`` x ``pixels`` rays the thesis' way (rays not bounded,
    the model's own sample counts) in ``parts`` parts, and our step (rendering with ``sampling``) before the
    first part and after each: the two ways share the machine's ups and downs in one run."""
    start = _starts(loaded, observed, candidates, seed)
    config, settings = OptimizerConfig(iterations=iterations), sampling.settings(loaded, observed.centre)

    def ours() -> Timing:
        return our_loop(loaded, start, observed.image, observed.intrinsics, pixels, observed.centre, config, seed,
                        settings)

    thesis = ThesisLoop(loaded, start, observed.image, observed.intrinsics, pixels, seed=seed)
    ours_runs = [ours()]
    for part in np.array_split(np.arange(iterations), min(parts, iterations)):
        thesis.run(len(part))
        ours_runs.append(ours())
    return PerfComparison(thesis.timing(), ours_runs)


@dataclass(frozen=True)
class SweepPoint:
    candidates: int
    pixels: int
    timing: Timing


@dataclass(frozen=True)
class Sweep:
    """How our step scales with the number of rays."""

    chunk_rays: int
    """Rays per chunk with ``sampling``'s sample counts."""
    memory_budget_bytes: int
    points: list[SweepPoint]


def sweep(loaded: LoadedModel, observed: ObservedFrame, points: Sequence[tuple[int, int]], iterations: int,
          sampling: Sampling, seed: int = 0) -> Sweep:
    """Time ours for each ``(candidates, pixels)`` of ``points``, ``iterations`` iterations each."""
    config = OptimizerConfig(iterations=iterations)
    settings = sampling.settings(loaded, observed.centre)
    timed = [SweepPoint(n, p, our_loop(loaded, _starts(loaded, observed, n, seed), observed.image,
                                       observed.intrinsics, p, observed.centre, config, seed, settings))
             for n, p in points]
    return Sweep(settings.chunk_rays or loaded.chunk_rays, memory_budget_bytes(loaded.device), timed)


@dataclass(frozen=True)
class OperatorTime:
    name: str
    self_cpu_s: float
    calls: int


@dataclass(frozen=True)
class Profile:
    """Where our step's time goes: the operators by the CPU time spent in themselves."""

    iterations: int
    cpu_s: float
    """CPU time in all operators."""
    operators: list[OperatorTime]
    """The ``top`` operators, most time first."""


def profile_ours(loaded: LoadedModel, observed: ObservedFrame, candidates: int, pixels: int, sampling: Sampling,
                 iterations: int = 5, top: int = 15, seed: int = 0) -> Profile:
    """Profile ``iterations`` of our iterations with ``torch.profiler``, after as many unprofiled ones to
    warm up (first-call costs are not where a long run spends its time)."""
    config = OptimizerConfig(iterations=iterations)
    start = _starts(loaded, observed, candidates, seed)
    settings = sampling.settings(loaded, observed.centre)
    our_loop(loaded, start, observed.image, observed.intrinsics, pixels, observed.centre, config, seed, settings)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
        our_loop(loaded, start, observed.image, observed.intrinsics, pixels, observed.centre, config, seed, settings)
    events = profile.key_averages()
    ranked = sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:top]
    return Profile(iterations, sum(e.self_cpu_time_total for e in events) / 1e6,
                   [OperatorTime(e.key, e.self_cpu_time_total / 1e6, e.count) for e in ranked])


@dataclass(frozen=True)
class LatencyRun:
    """One ``ns-invert --clock realtime`` run of the latency benchmark, with measured compute time."""

    clock_speed: float
    run: Path
    summary: RunSummary


@dataclass(frozen=True)
class LatencyRow:
    """The latency benchmark at one clock speed: medians over its runs."""

    clock_speed: float
    runs: int
    frames: int
    """Frames of the sequence the runs covered."""
    mean_latency_s: float
    """Median over the runs of each run's mean latency of its estimated frames."""
    max_latency_s: float
    frames_skipped: float
    time_to_first_lock_s: float | None
    """Median over the runs that locked (under 5 degrees); ``None`` when none did."""
    locked_runs: int
    rotation_mean_deg: float | None
    """Median of the runs' mean rotation error over every frame, interpolated ones included."""
    rotation_mean_estimated_deg: float | None
    """The same over the estimated frames alone."""
    under_5deg: float | None
    """Median share of the frames (all of them) under 5 degrees."""


def latency_runs(config: InvertConfig, speeds: Sequence[float], repeats: int,
                 events: Callable[[float, int], Events] = lambda speed, repeat: Events()) -> list[LatencyRun]:
    """``config`` run ``repeats`` times at each clock speed with ``--clock realtime`` and the compute time
    measured (no fixed cost), each in a new folder under ``config.output_dir / config.name``; ``events``
    gives each run's front end."""
    stamp = datetime.now().strftime("%Y-%m-%d_%H%M%S")
    runs = []
    for speed in speeds:
        for repeat in range(repeats):
            c = dataclasses.replace(config, clock="realtime", clock_speed=float(speed), clock_cost_s=None,
                                    timestamp=f"{stamp}-speed{speed:g}-run{repeat}")
            inversion = Inversion.create(c, events(speed, repeat))
            runs.append(LatencyRun(float(speed), inversion.folder.path, inversion.run()))
    return runs


def _median(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return float(np.median(known)) if known else None


def latency_rows(runs: Sequence[LatencyRun]) -> list[LatencyRow]:
    """One row per clock speed, in the order first run."""
    rows = []
    for speed in dict.fromkeys(r.clock_speed for r in runs):
        summaries = [r.summary for r in runs if r.clock_speed == speed]
        rotation = [None if s.rotation_deg is None else s.rotation_deg.mean for s in summaries]
        estimated = [s.estimated_only.rotation_deg.mean if s.estimated_only is not None else rot
                     for s, rot in zip(summaries, rotation)]
        rows.append(LatencyRow(
            clock_speed=speed, runs=len(summaries), frames=summaries[0].frames_done,
            mean_latency_s=float(np.median([s.latency_s.mean for s in summaries])),
            max_latency_s=float(np.median([s.latency_s.max for s in summaries])),
            frames_skipped=float(np.median([s.frames_skipped for s in summaries])),
            time_to_first_lock_s=_median([s.time_to_first_lock_s for s in summaries]),
            locked_runs=sum(s.time_to_first_lock_s is not None for s in summaries),
            rotation_mean_deg=_median(rotation), rotation_mean_estimated_deg=_median(estimated),
            under_5deg=_median([None if s.success_rotation is None else s.success_rotation["5deg"]
                                for s in summaries])))
    return rows
