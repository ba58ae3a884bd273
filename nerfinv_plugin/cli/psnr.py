"""``ns-invert-psnr``: how well a trained model renders the held-out views of a Blender-format dataset."""

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from rich.console import Console

from nerfinv_plugin.cli import run
from nerfinv_plugin.model.evaluate import evaluate_split
from nerfinv_plugin.model.loading import Device, ModelLoadError, load_model


@dataclass
class HeldOutPSNR:
    """Render every view of a split of a Blender-format dataset (transforms_<split>.json) with a trained
    model and print the PSNR of each against its image. Inversion can only be as good as these renders."""

    load_config: Path
    """config.yml of the trained run (outputs/<experiment>/<method>/<timestamp>/config.yml)."""
    data: Path
    """Dataset folder holding transforms_<split>.json and the images."""
    split: Literal["train", "val", "test"] = "test"
    """Which views to score."""
    device: Device = "auto"
    """Where to render: cuda when available under auto."""

    def main(self) -> None:
        console = Console()
        loaded = load_model(self.load_config, device=self.device)
        scores = evaluate_split(loaded, self.data, self.split)
        for score in scores:
            console.print(f"{score.file.name}: {score.psnr:.2f} dB")
        values = np.array([s.psnr for s in scores])
        console.print(f"[bold]{self.split}: mean PSNR {values.mean():.2f} dB over {len(values)} views "
                      f"(min {values.min():.2f}, max {values.max():.2f}); model step {loaded.step}[/bold]")


def entrypoint() -> None:
    run(HeldOutPSNR, "ns-invert-psnr", ModelLoadError, FileNotFoundError)


if __name__ == "__main__":
    entrypoint()
