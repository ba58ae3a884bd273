"""The CUDA path against the CPU one, and a GPU row for the throughput tables (``ns-invert-bench gpu``).

Everything the tests check runs on the CPU; a GPU machine is lent to this project rarely and never to its
tests. So one prepared check, run where a GPU is: the same model loaded on both devices renders the same
candidates at the same pixels, with rays bounded as ``ns-invert`` bounds them, and the colours, the
accumulations and the gradients of one loss with respect to the poses must agree within float32 tolerances
(the CPU uses the compiled kernels, CUDA nerfstudio's torch path: two implementations of one function).
Then the throughput benchmark of ``ns-invert-bench perf`` runs on the GPU, and the view bank is rendered
there, forward only, for the table's row.
"""

import time
from dataclasses import dataclass

import numpy as np
import torch
from rich.console import Console

from nerfinv_plugin.bench.observed import ObservedFrame, read_observed
from nerfinv_plugin.bench.perf import MB, compare_loops, model_header
from nerfinv_plugin.bench.sampling import Sampling
from nerfinv_plugin.initialization.bank import BankConfig, render_bank
from nerfinv_plugin.initialization.extent import framed_radius
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.model.render import render

START_MIN_DEG, START_MAX_DEG, START_SHIFT_M = 5.0, 15.0, 0.05
"""The compared candidates: near the truth, so that their rays see the object and the gradients say something."""
RGB_ATOL = 1e-3
"""Colours and accumulations (on [0, 1]) may differ by this much: float32 sums in another order, and sample
depths placed by searchsorted on densities that differ in their last bits."""
GRADIENT_RTOL = 1e-2
"""The pose gradients may differ by this fraction of their largest entry."""


@dataclass(frozen=True)
class DeviceAgreement:
    """How far one device's renders and pose gradients are from another's, on the same candidates and pixels."""

    rays: int
    rgb_max_abs: float
    accumulation_max_abs: float
    gradient_max_rel: float
    """Largest difference of the pose gradients over the largest entry of the reference's."""
    gradient_scale: float
    """The reference's largest gradient entry: zero would mean the comparison said nothing."""

    @property
    def agrees(self) -> bool:
        return (self.rgb_max_abs <= RGB_ATOL and self.accumulation_max_abs <= RGB_ATOL
                and self.gradient_max_rel <= GRADIENT_RTOL and self.gradient_scale > 0.0)


def render_with_gradient(loaded: LoadedModel, c2w: torch.Tensor, observed: ObservedFrame, pixels: torch.Tensor,
                          sampling: Sampling) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colours, accumulations and the gradient of their photometric loss with respect to the poses, on CPU arrays.

    The poses are copied into a fresh leaf: marking the caller's tensor would make the next device's copy of it
    a non-leaf (no gradient kept, on CUDA), and on the CPU the two calls' gradients would pile up in one
    tensor that both returned arrays share."""
    leaf = c2w.detach().to(loaded.device, copy=True).requires_grad_(True)
    out = render(loaded, leaf, observed.intrinsics, pixels.to(loaded.device),
                 sampling.settings(loaded, observed.centre.to(loaded.device)))
    colours = torch.as_tensor(observed.image, dtype=torch.float32, device=loaded.device)[
        pixels[:, 0].to(loaded.device), pixels[:, 1].to(loaded.device)] / 255.0
    ((out.rgb - colours) ** 2).mean().backward()
    accumulation = out.accumulation if out.accumulation is not None else torch.zeros_like(out.rgb[..., :1])
    return (out.rgb.detach().cpu().numpy(), accumulation.detach().cpu().numpy(), leaf.grad.cpu().numpy())


def compare_devices(reference: LoadedModel, other: LoadedModel, observed: ObservedFrame, candidates: int,
                    pixels: int, sampling: Sampling, seed: int = 0) -> DeviceAgreement:
    """Render ``candidates`` poses near the frame's truth at ``pixels`` random pixels on both models (the same
    checkpoint loaded on two devices) and measure how far ``other``'s results are from ``reference``'s."""
    start = observed.starts(candidates, START_MIN_DEG, START_MAX_DEG,
                            START_SHIFT_M * reference.dataparser_scale, seed).cpu()
    rng = np.random.default_rng(seed)
    height, width = observed.image.shape[:2]
    chosen = torch.as_tensor(np.stack([rng.integers(0, height, pixels), rng.integers(0, width, pixels)], 1))
    rgb_a, acc_a, grad_a = render_with_gradient(reference, start, observed, chosen, sampling)
    rgb_b, acc_b, grad_b = render_with_gradient(other, start, observed, chosen, sampling)
    scale = float(np.abs(grad_a).max())
    return DeviceAgreement(candidates * pixels, float(np.abs(rgb_b - rgb_a).max()), float(np.abs(acc_b - acc_a).max()),
                           float(np.abs(grad_b - grad_a).max() / scale) if scale > 0 else float("inf"), scale)


def bank_throughput(loaded: LoadedModel, observed: ObservedFrame, sampling: Sampling,
                    config: BankConfig | None = None) -> tuple[float, float]:
    """Seconds to render the view bank (default: ns-invert's) on ``loaded``'s device, forward only, and its rays
    per second."""
    config = config or BankConfig()
    settings = sampling.settings(loaded, observed.centre.to(loaded.device))
    radius = framed_radius(loaded, observed.centre, settings)  # what ns-invert's bank frames under these settings
    if loaded.device.type == "cuda":
        torch.cuda.synchronize(loaded.device)
    tic = time.perf_counter()
    render_bank(loaded, settings, observed.centre.cpu().numpy().astype(np.float64), radius, config)
    if loaded.device.type == "cuda":
        torch.cuda.synchronize(loaded.device)
    seconds = time.perf_counter() - tic
    return seconds, config.views * config.render_px**2 / seconds


@dataclass(frozen=True)
class GpuCheck:
    """What ``ns-invert-bench gpu`` measures: one frame of a sequence with ground truth, the throughput
    comparison's sizes (the thesis': 15 candidates x 256 pixels x 60 iterations) and our ray sampling."""

    load_config: str
    sequence: str
    frame: int = 0
    resolution: tuple[int, int] | None = None
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    candidates: int = 15
    pixels: int = 256
    iterations: int = 60
    seed: int = 0
    sampling: Sampling = Sampling()


def gpu_check(check: GpuCheck, console: Console) -> bool:
    """Load ``check.load_config`` on the CPU and on CUDA, compare their renders and pose gradients, and, when
    they agree, print the GPU row of the throughput table (perf's comparison and the view bank's forward-only
    build on the GPU). Returns whether the devices agreed.

    Kept apart from the bench command's front end, whose imports (the synthetic-scene renderer among them)
    a GPU machine need not have."""
    cpu, gpu = load_model(check.load_config, device="cpu"), load_model(check.load_config, device="cuda")
    observed = read_observed(cpu, check.sequence, check.frame, check.target, check.resolution)
    name = torch.cuda.get_device_name(gpu.device)
    console.print(f"{model_header(gpu, check.load_config)} ({name}); frame {observed.name}")
    agreement = compare_devices(cpu, gpu, observed, check.candidates, check.pixels, check.sampling, check.seed)
    console.print(f"CUDA against CPU on {agreement.rays:,} rays: colour {agreement.rgb_max_abs:.2e}, accumulation "
                  f"{agreement.accumulation_max_abs:.2e} (max abs), pose gradient {agreement.gradient_max_rel:.2e} "
                  f"of its largest entry {agreement.gradient_scale:.3g}: "
                  + ("[bold green]agree[/bold green]" if agreement.agrees else "[bold red]DISAGREE[/bold red]"))
    if not agreement.agrees:
        return False
    compared = compare_loops(gpu, observed, check.candidates, check.pixels, check.iterations, check.sampling,
                             check.seed)
    bank_s, bank_rays = bank_throughput(gpu, observed, check.sampling)
    thesis, ours = compared.thesis, compared.ours
    console.print("| device | thesis s / iteration | nerfinv s / iteration | ratio | nerfinv rays / s | "
                  "peak memory, thesis / ours | bank (642 views, forward only) |\n|---|---|---|---|---|---|---|")
    console.print(f"| {name} | {thesis.per_iteration:.3f} | {ours.per_iteration:.4f} | {compared.ratio:.2f}x | "
                  f"{ours.rays_per_second:,.0f} | {thesis.peak_memory_bytes / MB:,.0f} / "
                  f"{ours.peak_memory_bytes / MB:,.0f} MB | {bank_s:.1f} s, {bank_rays:,.0f} rays/s |")
    return True
