"""``ns-invert-bench-screw``: screw motions about the target centre against the thesis' plain form.

nerfstudio's auto-centred model frame puts the origin at the mean camera position, and a Blender-frame
model at the dataset origin; neither is where the target is. ``exp([S] theta) T0`` then couples rotation
and translation through the distance to that origin. This compares both parameterisations from the same
starts on the same frame, in one process.
"""

import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from rich.console import Console

from nerfinv_plugin.cli import run
from nerfinv_plugin.data.sequences import SequenceError, read_sequence
from nerfinv_plugin.geometry.se3 import geodesic_deg
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.starts import inerf_protocol_starts
from nerfinv_plugin.inversion.tracker import Frame, MonteCarloConfig, Tracker
from nerfinv_plugin.model.loading import Device, ModelLoadError, load_model


@dataclass
class ScrewBenchmark:
    """Optimize the same starts on one frame with both screw parameterisations; print final errors."""

    load_config: Path
    """config.yml of a trained run whose dataset frame is the target body frame."""
    sequence: str
    """A sequence of the same object with ground truth: a SHIRT trajectory (<root>/roeN[/domain]), a Blender
    split (<scene>:<split>) or an image folder with camera.json and poses.json."""
    frame: int = 0
    """Which frame to invert."""
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
    """Repetitions with different starts and pixels."""
    device: Device = "auto"
    """Where to render."""

    def main(self) -> None:
        console = Console()
        loaded = load_model(self.load_config, device=self.device)
        seq = read_sequence(self.sequence, start=self.frame, stop=self.frame + 1)
        observed = seq.frames[0]
        if observed.c2w_true is None:
            raise SequenceError(f"frame {self.frame} of {self.sequence} has no ground-truth pose; this benchmark "
                                "needs one (add it to poses.json, or use a SHIRT or Blender sequence)")
        truth = torch.as_tensor(loaded.dataset_to_model(observed.c2w_true), dtype=torch.float32)
        frame = Frame(observed.image, seq.intrinsics, observed.name, truth)
        centre = torch.as_tensor(loaded.point_to_model(np.zeros(3)), dtype=torch.float32)
        # The camera's distance from the target origin: the true range of a SHIRT label.
        target_range = float(np.linalg.norm(observed.c2w_true[:3, 3]))
        shift = self.shift_fraction * target_range * loaded.dataparser_scale
        results: dict[str, list[tuple[float, float]]] = {"target": [], "world": []}
        for seed in range(self.seeds):
            start = inerf_protocol_starts(truth, centre, self.candidates, self.min_deg, self.max_deg, shift, seed)
            for origin in results:
                results[origin].append(self._run(loaded, frame, centre, start, origin, seed))
        console.print(f"{self.sequence} frame {self.frame}, {self.candidates} candidates, {self.iterations} "
                      f"iterations, starts {self.min_deg:g}-{self.max_deg:g} deg and {self.shift_fraction:.0%} of "
                      f"the range off, {self.seeds} seeds")
        console.print("| screw about | best error, deg (median over seeds) | all candidates' median error, deg "
                      "| s per step |\n|---|---|---|---|")
        for origin, rows in results.items():
            best, median, seconds = zip(*rows)
            console.print(f"| {origin} | {statistics.median(best):.2f} | {statistics.median(median):.2f} | "
                          f"{statistics.median(seconds):.1f} |")

    def _run(self, loaded, frame: Frame, centre: torch.Tensor, start: torch.Tensor,
             origin: Literal["target", "world"], seed: int) -> tuple[float, float, float]:
        tracker = Tracker(loaded, centre, OptimizerConfig(iterations=self.iterations, screw_origin=origin),
                          MonteCarloConfig(), seed=seed)
        began = time.perf_counter()
        record = tracker.run([frame], start, steps=1)[0]
        seconds = time.perf_counter() - began
        truth = frame.c2w_true[:3, :3]
        errors = geodesic_deg(record.result.c2w[:, :3, :3], truth.expand_as(record.result.c2w[:, :3, :3]))
        best = float(geodesic_deg(record.estimate[:3, :3], truth))
        return best, float(errors.median()), seconds


def entrypoint() -> None:
    run(ScrewBenchmark, "ns-invert-bench-screw", ModelLoadError, SequenceError)


if __name__ == "__main__":
    entrypoint()
