"""``ns-invert-psnr``: how well a trained model renders the held-out views of the data it was trained on."""

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from rich.console import Console
from rich.markup import escape

from nerfinv_plugin.cli import run
from nerfinv_plugin.inversion.validation import SettingsError, check, whole
from nerfinv_plugin.model.evaluate import DataFormatError, FormatChoice, SplitScore, score_split
from nerfinv_plugin.model.loading import Device, ModelLoadError, load_model

RULES = {"max-views": whole(1)}
"""What the numeric options accept (nerfinv_plugin/inversion/validation.py)."""

LOW_MARGIN_DB = 1.0
"""Below this margin over an all-black image the model has most likely learned nothing of the object."""


@dataclass
class HeldOutPSNR:
    """Render the held-out views of a dataset with a trained model and print the PSNR of each against its
    image, beside the PSNR an all-black image scores on the same views: on a dark background that alone is
    high, and only the margin above it says the model learned the object. Inversion can only be as good as
    these renders. Reads Blender (transforms_<split>.json), nerfstudio (transforms.json) and SPEED+
    (camera.json, synthetic/validation.json) data, with the held-out views each dataparser uses."""

    load_config: Path
    """config.yml of the trained run (outputs/<experiment>/<method>/<timestamp>/config.yml)."""
    data: Path
    """Dataset folder: the one passed to ns-train --data."""
    format: FormatChoice = "auto"
    """Layout of --data. auto: Blender if it holds transforms_<split>.json, else nerfstudio if it holds
    transforms.json, else SPEED+ if it holds synthetic/validation.json or camera.json and synthetic/."""
    split: Literal["train", "val", "test"] = "test"
    """Which views to score. nerfstudio: <split>_filenames of transforms.json (val and test fall back on each
    other), else the run's eval-mode split (fraction 0.9 by default), where val and test are the same views.
    SPEED+: speedplus-data's split (validation.json for val and test in the synthetic domain)."""
    max_views: int | None = None
    """Score at most this many views, spread evenly over the split (SPEED+ validation has 11,994)."""
    device: Device = "auto"
    """Where to render: cuda when available under auto."""

    def main(self) -> None:
        check(self, RULES)
        console = Console(soft_wrap=True)  # one line a view, however narrow the terminal
        loaded = load_model(self.load_config, device=self.device)
        score = score_split(loaded, self.data, self.format, self.split, self.max_views)
        print_score(console, score, self.data, loaded.step)


def print_score(console: Console, score: SplitScore, data: Path, step: int) -> None:
    """Per-view lines, then the mean beside the all-black baseline and the margin."""
    root = data if data.is_dir() else data.parent
    for view in score.views:
        name = view.file.relative_to(root) if view.file.is_relative_to(root) else view.file
        console.print(f"{escape(str(name))}: {view.psnr:.2f} dB (all-black {view.black_psnr:.2f} dB)")
    values = np.array([view.psnr for view in score.views])
    console.print(f"[bold]{score.split} ({score.format}, {escape(score.source)}): mean PSNR {score.mean_psnr:.2f} "
                  f"dB over {len(values)} views (min {values.min():.2f}, max {values.max():.2f}); all-black "
                  f"{score.black_psnr:.2f} dB; margin {score.margin_db:+.2f} dB; model step {step}[/bold]")
    if score.margin_db < LOW_MARGIN_DB:
        console.print(f"[yellow]The model scores within {LOW_MARGIN_DB:.0f} dB of an all-black image: it probably "
                      "renders (almost) nothing. Check the background setting, near/far planes and scene box "
                      "(docs/nerfacto-tiny.md).[/yellow]")


def entrypoint() -> None:
    run(HeldOutPSNR, "ns-invert-psnr", SettingsError, ModelLoadError, FileNotFoundError, DataFormatError)


if __name__ == "__main__":
    entrypoint()
