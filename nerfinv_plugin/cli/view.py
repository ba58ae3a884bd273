"""``ns-invert-view``: replay an ``ns-invert`` run in nerfstudio's viewer (viser), from its files."""

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console
from rich.markup import escape

from nerfinv_plugin.cli import run
from nerfinv_plugin.inversion.validation import PORT, SettingsError, check, number
from nerfinv_plugin.model.loaded import ModelLoadError
from nerfinv_plugin.model.loading import Device
from nerfinv_plugin.viewer.live import start_server, viewer_url
from nerfinv_plugin.viewer.replay import Replay, ReplayError

RULES = {"port": PORT, "interval-s": number(at_least=0)}
"""What the numeric options accept (nerfinv_plugin/inversion/validation.py)."""
POLL_S = 1.0
"""How often a run that is still going is looked at for new steps."""


@dataclass
class View:
    """Replay an ns-invert run in nerfstudio's viewer: the model's training cameras, the observed frame,
    the candidates of every step coloured by loss, the ones each step kept, and the estimated trajectory
    against the truth. A run still going on is followed: its new steps are drawn as they are written.
    Open the printed URL in a browser; Ctrl-C stops."""

    run_dir: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """The run folder ns-invert printed after 'results:' (outputs/<name>/nerfinv/<timestamp>)."""
    port: int | None = None
    """Port of the viewer. Default: 7007, or a free port when it is taken, as ns-train does."""
    interval_s: float = 0.1
    """Seconds between two drawn snapshots of the candidates (the trail records one every 5 iterations)."""
    render: bool = True
    """Load the model and show its render at the best candidate of every step beside the observed image."""
    device: Device = "cpu"
    """Where to render (a small image per step: the CPU is enough)."""

    def main(self) -> None:
        check(self, RULES)
        console = Console()
        server = start_server(self.port)
        try:
            replay = Replay.open(self.run_dir, server, self.interval_s, self.render, self.device,
                                 warn=lambda message: console.print(f"[yellow]{escape(message)}[/yellow]"))
            console.print(viewer_url(server))
            announced = False
            while True:
                if replay.play_new() == 0:
                    if replay.complete() and not announced:
                        console.print(f"replayed {replay.steps_drawn} steps; the run is complete (Ctrl-C to stop)")
                        announced = True
                    time.sleep(POLL_S)
        except KeyboardInterrupt:
            console.print("viewer stopped")
        finally:
            server.stop()


def entrypoint() -> None:
    run(View, "ns-invert-view", ReplayError, SettingsError, ModelLoadError)


if __name__ == "__main__":
    entrypoint()
