"""What ``ns-invert --viewer`` costs an inversion: the same run without the viewer and with it (model render
off) while one headless Chromium (SwiftShader WebGL, as the browser tests) watches, alternated ``--repeats``
times so that a change in the machine's load falls on both. Prints every run's inversion time (the run's
own ``wall_time_s``: model loading and the report are not counted) and the ratio of the medians.

    python tools/viewer_overhead.py CONFIG_YML SEQUENCE [--target X Y Z] [--stop N] [--repeats R]

Needs the test extra (selenium) and Debian's chromium + chromium-driver.
"""

import io
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the browser the tests drive
from browser import chromium  # noqa: E402

from nerfinv_plugin.cli.invert import invert  # noqa: E402
from nerfinv_plugin.inversion.optimizer import OptimizerConfig  # noqa: E402
from nerfinv_plugin.inversion.settings import InvertConfig, StartConfig  # noqa: E402
from nerfinv_plugin.inversion.tracker import MonteCarloConfig  # noqa: E402
from nerfinv_plugin.viewer.live import LiveViewer, start_server  # noqa: E402


@dataclass
class Overhead:
    load_config: Annotated[Path, tyro.conf.Positional]
    """config.yml of the trained model."""
    sequence: Annotated[str, tyro.conf.Positional]
    """The observed sequence (as ns-invert --sequence)."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    stop: int = 4
    """Frames inverted per run."""
    repeats: int = 3
    """Pairs of runs (without, with the viewer)."""
    iterations: int = 30

    def config(self, out: Path, timestamp: str) -> InvertConfig:
        return InvertConfig(load_config=self.load_config, sequence=self.sequence, output_dir=out, name="overhead",
                            timestamp=timestamp, device="cpu", target=self.target, stop=self.stop, pixels=128,
                            eval_pixels=512, starts=StartConfig(source="truth-offset", count=6, min_deg=15.0,
                                                                max_deg=20.0, shift_m=0.25),
                            optimizer=OptimizerConfig(iterations=self.iterations),
                            monte_carlo=MonteCarloConfig(keep=(2, 1), spawn=2))

    def main(self) -> None:
        quiet = Console(file=io.StringIO())
        times: dict[str, list[float]] = {"without viewer": [], "viewer, one browser": []}
        with tempfile.TemporaryDirectory() as out:
            for repeat in range(self.repeats):
                summary = invert(self.config(Path(out), f"off-{repeat}"), quiet)
                times["without viewer"].append(summary.wall_time_s)
                server = start_server(None)
                try:
                    with chromium() as browser:
                        browser.get(f"http://localhost:{server.get_port()}")
                        while not server.get_clients():
                            time.sleep(0.1)
                        summary = invert(self.config(Path(out), f"on-{repeat}"), quiet,
                                         LiveViewer(server, render=False))
                        clients = len(server.get_clients())
                finally:
                    server.stop()
                assert clients == 1, f"the browser was not connected at the end of the run ({clients} clients)"
                times["viewer, one browser"].append(summary.wall_time_s)
                print(f"pair {repeat}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in times.items()), flush=True)
        off, on = (statistics.median(v) for v in times.values())
        print(f"median without viewer {off:.2f} s, with the viewer and one browser {on:.2f} s: ratio {on / off:.3f}")


if __name__ == "__main__":
    tyro.cli(Overhead).main()
