"""``ns-invert-report``: the report of an ``ns-invert`` run, as a page that opens from disk."""

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console
from rich.markup import escape

from nerfinv_plugin.cli import run
from nerfinv_plugin.inversion.validation import SettingsError, check, several, whole
from nerfinv_plugin.model.loading import Device
from nerfinv_plugin.report.build import ReportError, write_report

RULES = {"frames": several(whole(0), empty=True)}
"""What the numeric options accept (nerfinv_plugin/inversion/validation.py)."""


@dataclass
class ReportCommand:
    """Write report.html into an ns-invert run folder: error against time and iterations, the error of
    every frame, the estimate drawn over the observed images, the summary, a table of the frames and the
    run's settings. Figures go to RUN_DIR/report/. Runs again at any time, also on a run still going on."""

    run_dir: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """The run folder ns-invert printed after 'results:' (outputs/<name>/nerfinv/<timestamp>)."""
    overlays: bool = True
    """Render the model at the estimates for the overlay and filmstrip figures; needs the model and the
    sequence where the run's config.yml says they are (without them, the rest is still written)."""
    frames: tuple[int, ...] = ()
    """Sequence frame numbers (the 'frame' column of results.jsonl) for the overlay figure. Default: the
    first, middle and last frame done."""
    device: Device = "cpu"
    """Where to render the overlay images (a few full images: the CPU is enough)."""

    def main(self) -> None:
        check(self, RULES)
        console = Console()
        path = write_report(self.run_dir, self.overlays, self.device, self.frames or None,
                            warn=lambda message: console.print(f"[yellow]{escape(message)}[/yellow]"))
        console.print(f"report: {path}")


def entrypoint() -> None:
    run(ReportCommand, "ns-invert-report", ReportError, SettingsError)


if __name__ == "__main__":
    entrypoint()
