"""``ns-invert-bench-render``: forward+backward throughput of our batched renderer against the thesis'."""

import statistics
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
import torch
from rich.console import Console

from nerfinv_plugin.bench.perf import thesis_step
from nerfinv_plugin.cli import run
from nerfinv_plugin.inversion.optimizer import candidate_losses
from nerfinv_plugin.inversion.starts import sphere_shell
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.loading import Device, ModelLoadError, load_model
from nerfinv_plugin.model.render import (
    Intrinsics,
    bound_to_target,
    ray_bundle,
    render,
    set_sample_counts,
)
from nerfinv_plugin.synth.datasets import speedplus_like_camera


def batched_step(loaded: LoadedModel, c2w: torch.Tensor, intrinsics: Intrinsics, pixels: torch.Tensor,
                 target: torch.Tensor) -> torch.Tensor:
    """One iteration of our engine (``optimizer.candidate_losses``): all candidates' rays in chunked
    batches, frozen weights, each chunk's loss back-propagated before the next chunk is rendered."""
    return candidate_losses(loaded, c2w, intrinsics, pixels, target, "mse", backward=True)


@dataclass
class RenderBenchmark:
    """Time one inversion iteration (render N candidates at P pixels, loss, backward) done the thesis' way
    and our way, alternately in one process on the same rays, and print rays per second and the ratio."""

    load_config: Path
    """config.yml of a trained run."""
    candidates: int = 15
    """Candidate poses rendered per iteration (the thesis used 15)."""
    pixels: int = 256
    """Pixels sampled per candidate."""
    repeats: int = 5
    """Timed iterations of each way (after one warm-up each); the median is reported."""
    range_m: float = 5.0
    """Distance of the candidate cameras (random, looking at the dataset origin) in dataset units."""
    width: int = 240
    """Image width in pixels; the field of view is SPEED+'s."""
    height: int = 150
    """Image height in pixels."""
    device: Device = "auto"
    """Where to render."""
    seed: int = 0
    """Seeds candidate poses and pixels."""
    target_radius_m: float | None = 1.0
    """Our way: rays sampled only within this radius (dataset units) of the dataset origin, as ns-invert's
    --render.target-radius-m does. Unset: the model's near and far."""
    proposal_samples: tuple[int, ...] | None = (8, 4)
    """Our way: samples per ray of each proposal level (--render.proposal-samples). Unset: as trained."""
    nerf_samples: int | None = 8
    """Our way: samples per ray of the final field (--render.nerf-samples). Unset: as trained."""
    on_target: bool = False
    """Draw the pixels only where the first candidate's rays cross the target sphere (as interest-region
    pixels on the object are), instead of anywhere in the image, where many rays miss it and cost ours
    nothing."""

    def main(self) -> None:
        console = Console()
        loaded = load_model(self.load_config, device=self.device)
        rng = np.random.default_rng(self.seed)
        camera = speedplus_like_camera(self.width, self.height)
        intrinsics = Intrinsics.from_opencv(camera.matrix, self.width, self.height)
        poses = loaded.dataset_to_model(sphere_shell(self.candidates, self.range_m, np.zeros(3), rng))
        c2w = torch.as_tensor(poses[:, :3], dtype=torch.float32, device=loaded.device)
        sphere = None if self.target_radius_m is None else \
            (torch.as_tensor(loaded.point_to_model(np.zeros(3)), dtype=torch.float32, device=loaded.device),
             self.target_radius_m * loaded.dataparser_scale)
        allowed = np.arange(self.width * self.height)
        if self.on_target and sphere is not None:
            loaded.target_sphere = sphere
            everywhere = torch.as_tensor(np.stack([allowed // self.width, allowed % self.width], 1))
            hits = bound_to_target(loaded, ray_bundle(loaded, c2w[:1], intrinsics, everywhere))
            allowed = allowed[hits.cpu().numpy()]
            loaded.target_sphere = None
        flat = rng.choice(allowed, size=self.pixels, replace=False)
        pixels = torch.as_tensor(np.stack([flat // self.width, flat % self.width], 1), device=loaded.device)
        target = torch.zeros(self.pixels, 3, device=loaded.device)
        rays = self.candidates * self.pixels

        sampler = getattr(loaded.model, "proposal_sampler", None)
        trained = None if sampler is None else (sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray)

        def our_settings(on: bool) -> None:
            """Our inversion-time sampling on, or the model as trained (the thesis' way)."""
            loaded.target_sphere = sphere if on else None
            if trained is not None and (self.proposal_samples or self.nerf_samples):
                proposal, nerf = (self.proposal_samples, self.nerf_samples) if on else trained
                set_sample_counts(loaded, proposal, nerf)

        def timed(step, frozen: bool) -> tuple[float, torch.Tensor]:  # (seconds, what the step returns)
            leaf = c2w.clone().requires_grad_(True)
            loaded.model.requires_grad_(not frozen)
            our_settings(frozen)
            try:
                sync()
                start = time.perf_counter()
                result = step(loaded, leaf, intrinsics, pixels, target)
                sync()
                return time.perf_counter() - start, result
            finally:
                loaded.model.requires_grad_(False)
                loaded.model.zero_grad(set_to_none=True)

        def sync() -> None:
            if loaded.device.type == "cuda":
                torch.cuda.synchronize(loaded.device)

        _, rgb_thesis = timed(thesis_step, frozen=False)
        timed(batched_step, frozen=True)
        our_settings(True)
        with torch.no_grad():
            rgb_ours = render(loaded, c2w, intrinsics, pixels).rgb
        thesis_times, our_times = [], []
        for _ in range(self.repeats):
            thesis_times.append(timed(thesis_step, frozen=False)[0])
            our_times.append(timed(batched_step, frozen=True)[0])
        t_thesis, t_ours = statistics.median(thesis_times), statistics.median(our_times)
        diff = (rgb_thesis - rgb_ours).detach().abs()
        console.print(f"model {loaded.config.method_name} step {loaded.step}, device {loaded.device}, "
                      f"{self.candidates} candidates x {self.pixels} pixels = {rays} rays, "
                      f"chunk {loaded.chunk_rays} rays; ours: target radius {self.target_radius_m}, samples "
                      f"{self.proposal_samples} / {self.nerf_samples}; colour difference between the ways: "
                      f"mean {float(diff.mean()):.2e}, max {float(diff.max()):.2e}")
        console.print("| way | s / iteration (median) | rays / s (fwd+bwd) |\n|---|---|---|")
        console.print("| thesis: per-candidate get_outputs_for_camera_ray_bundle, stock hash forward, weights "
                      f"trainable | {t_thesis:.3f} | {rays / t_thesis:,.0f} |")
        console.print("| nerfinv: one batched bundle, chunked, fused hash forward, frozen weights, bounded rays | "
                      f"{t_ours:.3f} | {rays / t_ours:,.0f} |")
        console.print(f"ratio (thesis time / ours): [bold]{t_thesis / t_ours:.2f}x[/bold]  "
                      f"({datetime.now().isoformat(timespec='minutes')})")


def entrypoint() -> None:
    run(RenderBenchmark, "ns-invert-bench-render", ModelLoadError)


if __name__ == "__main__":
    entrypoint()
