"""``ns-invert-bench-bank``: the view bank's build time, match time and recall on sequences with truth."""

from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.progress import Progress

from nerfinv_plugin.bench.recall import bank_recall
from nerfinv_plugin.cli import run
from nerfinv_plugin.data.sequences import SequenceError, read_sequence
from nerfinv_plugin.initialization.bank import BankConfig, bank_file
from nerfinv_plugin.initialization.initializer import Initializer
from nerfinv_plugin.inversion.session import bound_rays
from nerfinv_plugin.inversion.settings import RenderConfig
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.loading import Device, ModelLoadError, load_model


@dataclass
class BankBenchmark:
    """Build (or read) the view bank of a trained model as ns-invert does, then match every frame of the
    given sequences that has ground truth and the object wholly in view, and print the share whose first
    hypothesis, and whose first --hypotheses, include one within --threshold-deg of the true attitude."""

    load_config: Path
    """config.yml of a trained run."""
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
    """Render the bank even when a cached one exists (to time the build)."""
    bank: BankConfig = field(default_factory=BankConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    device: Device = "auto"

    def main(self) -> None:
        console = Console()
        torch.set_grad_enabled(False)
        loaded = load_model(self.load_config, device=self.device)
        centre = torch.as_tensor(loaded.point_to_model(np.asarray(self.target)), dtype=torch.float32)
        tic = datetime.now()
        radius = bound_rays(loaded, centre, self.render)
        radius_s = (datetime.now() - tic).total_seconds()
        if self.rebuild and loaded.target_sphere is not None:
            self._forget_cache(loaded, centre)
        with Progress(console=console) as progress:
            def on_build(views: int):
                task = progress.add_task("view bank", total=views)
                return lambda done: progress.update(task, advance=done)

            tic = datetime.now()
            initializer = Initializer.create(loaded, centre.numpy().astype(np.float64), self.bank, on_build)
            total_s = (datetime.now() - tic).total_seconds()
        console.print(f"{datetime.now():%Y-%m-%d %H:%M}, model {self.load_config} (step {loaded.step}), "
                      f"{torch.get_num_threads()} torch threads")
        console.print(f"object radius {radius if radius is not None else self.render.target_radius_m:.3f} m "
                      f"({radius_s:.1f} s); bank {self.bank.views} views x {self.bank.in_plane} angles at "
                      f"{self.bank.render_px} px: " + (f"rendered in {initializer.build_s:.1f} s" if initializer.built
                                                     else "read from the cache") +
                      f", ready in {total_s:.1f} s ({len(initializer.entries.views)} entries)")
        console.print(f"| sequence | frames | left out | top-1 within {self.threshold_deg:g} deg | "
                      f"top-{self.hypotheses} | median best error (deg) | median range error (top-1) | "
                      "match s (median, max) |")
        console.print("|---|---|---|---|---|---|---|---|")
        all1, allk = [], []
        for spec in self.sequences:
            sequence = read_sequence(spec, resolution=self.resolution)
            recall = bank_recall(loaded, initializer, sequence, spec, self.hypotheses, self.threshold_deg)
            all1 += [recall.top1] * recall.frames
            allk += [recall.topk] * recall.frames
            times = recall.match_s or [float("nan")]
            console.print(f"| {spec} | {recall.frames} | {recall.skipped} | {100 * recall.top1:.0f}% | "
                          f"{100 * recall.topk:.0f}% | {recall.median_best_deg:.1f} | "
                          f"{100 * recall.median_range_error:.1f}% | {np.median(times):.3f}, {max(times):.3f} |")
        if allk:
            console.print(f"[bold]all {len(allk)} frames: top-1 {100 * np.mean(all1):.1f}%, "
                          f"top-{self.hypotheses} {100 * np.mean(allk):.1f}%[/bold]")

    def _forget_cache(self, loaded: LoadedModel, centre: torch.Tensor) -> None:
        bank_file(loaded, centre.numpy().astype(np.float64), float(loaded.target_sphere[1]), self.bank).unlink(
            missing_ok=True)


def entrypoint() -> None:
    run(BankBenchmark, "ns-invert-bench-bank", ModelLoadError, SequenceError)


if __name__ == "__main__":
    entrypoint()
