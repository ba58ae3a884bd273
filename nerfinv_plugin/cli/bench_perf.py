"""``ns-invert-bench-perf``: inversion throughput of the thesis' implementation and ours, and how ours scales."""

from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path

import numpy as np
import torch
from rich.console import Console

from nerfinv_plugin.bench.perf import Timing, our_loop, thesis_loop
from nerfinv_plugin.cli import run
from nerfinv_plugin.data.sequences import SequenceError, read_sequence
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.starts import inerf_protocol_starts
from nerfinv_plugin.model.loading import Device, ModelLoadError, load_model
from nerfinv_plugin.model.render import memory_budget_bytes, set_sample_counts

MB = 1 << 20


@dataclass
class PerfBenchmark:
    """Run one Monte Carlo step (N candidates x P pixels x iterations) on one frame the thesis' way and
    ours, one after the other in this process, and print time per iteration, rays per second, peak memory
    and the ratio. With --sweep, time ours over candidate and pixel counts instead."""

    load_config: Path
    """config.yml of a trained run."""
    sequence: str
    """A sequence with ground truth (ns-invert's --sequence); the starts are placed around its frame."""
    frame: int = 0
    """Which frame of the sequence to invert."""
    resolution: tuple[int, int] | None = None
    """Working resolution WIDTH HEIGHT (default: the images' own)."""
    candidates: int = 15
    """Candidates per step (the thesis: 15)."""
    pixels: int = 256
    """Pixels per candidate and iteration."""
    iterations: int = 60
    """Iterations per step (the thesis: 60)."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Target centre in the dataset frame."""
    target_radius_m: float | None = 1.0
    """Ours: rays bounded to this radius about the target (ns-invert --render.target-radius-m)."""
    proposal_samples: tuple[int, ...] | None = (8, 4)
    """Ours: proposal samples per ray (--render.proposal-samples)."""
    nerf_samples: int | None = 8
    """Ours: field samples per ray (--render.nerf-samples)."""
    sweep: bool = False
    """Time ours for 1 to 80 candidates and 64 to 4096 pixels (sweep-iterations each) instead."""
    sweep_iterations: int = 5
    """Iterations per point of the sweep."""
    profile: bool = False
    """Profile 5 of our iterations with torch.profiler instead and print the operators that take the most
    CPU time (where the time goes)."""
    device: Device = "auto"
    """Where to render."""
    seed: int = 0
    """Seeds the starting poses and the pixels."""

    def main(self) -> None:
        console = Console()
        loaded = load_model(self.load_config, device=self.device)
        sequence = read_sequence(self.sequence, self.frame, self.frame + 1, 1, self.resolution)
        frame = sequence.frames[0]
        if frame.c2w_true is None:
            raise SequenceError(f"{self.sequence}: frame {self.frame} has no ground truth to place the starts around")
        truth = torch.as_tensor(loaded.dataset_to_model(frame.c2w_true), dtype=torch.float32)
        centre = torch.as_tensor(loaded.point_to_model(np.asarray(self.target)), dtype=torch.float32)

        def starts(count: int) -> torch.Tensor:
            return inerf_protocol_starts(truth, centre, count, 15.0, 20.0, 0.05 * loaded.dataparser_scale, self.seed)

        sampler = loaded.model.proposal_sampler
        trained = (sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray)
        config = OptimizerConfig(iterations=self.iterations)
        console.print(f"model {loaded.config.method_name} step {loaded.step} on {loaded.device}; frame "
                      f"{frame.name} at {sequence.intrinsics.width}x{sequence.intrinsics.height}; "
                      f"{datetime.now().isoformat(timespec='minutes')}")

        def ours() -> None:
            if self.target_radius_m is not None:
                loaded.target_sphere = (centre.to(loaded.device), self.target_radius_m * loaded.dataparser_scale)
            set_sample_counts(loaded, self.proposal_samples or trained[0], self.nerf_samples or trained[1])

        if self.sweep:
            ours()
            self._sweep(console, loaded, starts, frame.image, sequence.intrinsics, centre, config)
            return
        if self.profile:
            ours()
            self._profile(console, loaded, starts(self.candidates), frame.image, sequence.intrinsics, centre, config)
            return
        thesis = thesis_loop(loaded, starts(self.candidates), frame.image, sequence.intrinsics, self.pixels,
                             self.iterations, seed=self.seed)
        ours()
        mine = our_loop(loaded, starts(self.candidates), frame.image, sequence.intrinsics, self.pixels, centre,
                        config, self.seed)
        console.print(f"{self.candidates} candidates x {self.pixels} pixels x {self.iterations} iterations")
        console.print("| way | s / iteration | rays / s (fwd+bwd) | peak memory |\n|---|---|---|---|")
        for name, t in (("thesis (per-candidate patched get_outputs_for_camera_ray_bundle, trainable weights, "
                         "keypoints every iteration)", thesis), ("nerfinv (ns-invert's step)", mine)):
            console.print(f"| {name} | {t.per_iteration:.3f} | {t.rays_per_second:,.0f} | "
                          f"{t.peak_memory_bytes / MB:,.0f} MB |")
        ratio = thesis.per_iteration / mine.per_iteration
        console.print(f"ratio (thesis time per iteration / ours): [bold]{ratio:.2f}x[/bold]")

    def _sweep(self, console: Console, loaded, starts, image, intrinsics, centre, config: OptimizerConfig) -> None:
        short = replace(config, iterations=self.sweep_iterations)
        budget = memory_budget_bytes(loaded.device)
        console.print(f"chunk {loaded.chunk_rays} rays, memory budget {budget / MB:,.0f} MB")
        console.print("| candidates | pixels | rays / iteration | s / iteration | us / ray | peak memory |\n"
                      "|---|---|---|---|---|---|")
        points = [(n, self.pixels) for n in (1, 5, 15, 40, 80)] + \
            [(self.candidates, p) for p in (64, 1024, 4096)]
        for n, p in points:
            t: Timing = our_loop(loaded, starts(n), image, intrinsics, p, centre, short, self.seed)
            console.print(f"| {n} | {p} | {n * p:,} | {t.per_iteration:.3f} | "
                          f"{1e6 * t.per_iteration / (n * p):.1f} | {t.peak_memory_bytes / MB:,.0f} MB |")

    def _profile(self, console: Console, loaded, start, image, intrinsics, centre, config: OptimizerConfig) -> None:
        short = replace(config, iterations=5)
        our_loop(loaded, start, image, intrinsics, self.pixels, centre, short, self.seed)  # warm-up
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
            our_loop(loaded, start, image, intrinsics, self.pixels, centre, short, self.seed)
        events = profile.key_averages()
        total = sum(e.self_cpu_time_total for e in events)
        console.print(f"{self.candidates} candidates x {self.pixels} pixels x 5 iterations: "
                      f"{total / 1e6:.2f} s of CPU time in operators")
        console.print("| operator | self CPU time | share | calls |\n|---|---|---|---|")
        for event in sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:15]:
            console.print(f"| {event.key} | {event.self_cpu_time_total / 1e6:.3f} s | "
                          f"{100 * event.self_cpu_time_total / total:.1f}% | {event.count} |")


def entrypoint() -> None:
    run(PerfBenchmark, "ns-invert-bench-perf", ModelLoadError, SequenceError)


if __name__ == "__main__":
    entrypoint()
