"""What ``ns-invert --viewer`` costs an inversion: the same run without the viewer and with it (model render
off) while one headless Chromium (SwiftShader WebGL, as the browser tests) watches, alternated ``--repeats``
times so that a change in the machine's load falls on both. Prints every run's inversion time (the run's
own ``wall_time_s``: model loading and the report are not counted), the CPU time of this process over the
whole ``invert`` call (all its threads, viser's among them; loading and the report are the same in both,
so the difference is the viewer's own work, which a busy machine's load does not blur), the CPU time the
browser's processes took meanwhile (software WebGL on the same cores), and the ratios of the medians.

    python tools/viewer_overhead.py CONFIG_YML SEQUENCE [--target X Y Z] [--stop N] [--repeats R]

Needs the test extra (selenium) and Debian's chromium + chromium-driver.
"""

import io
import os
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


def tree_cpu_s(root: int) -> float:
    """CPU seconds (user + system) of every live process under ``root`` (Linux ``/proc``)."""
    stats = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:  # the process ended meanwhile
                continue
            stats[int(entry.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"))
    under, total = {root}, 0.0
    for _ in range(8):  # chromedriver -> chromium -> its zygote, renderer and GPU processes
        under |= {pid for pid, (parent, _) in stats.items() if parent in under}
    for pid in under:
        total += stats.get(pid, (0, 0.0))[1]
    return total


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
        cpu: dict[str, list[float]] = {"without viewer": [], "viewer, one browser": []}
        with tempfile.TemporaryDirectory() as out:
            for repeat in range(self.repeats):
                tic = time.process_time()
                summary = invert(self.config(Path(out), f"off-{repeat}"), quiet)
                cpu["without viewer"].append(time.process_time() - tic)
                times["without viewer"].append(summary.wall_time_s)
                server = start_server(None)
                try:
                    with chromium() as browser:
                        browser.get(f"http://localhost:{server.get_port()}")
                        while not server.get_clients():
                            time.sleep(0.1)
                        tic, browser_tic = time.process_time(), tree_cpu_s(browser.service.process.pid)
                        summary = invert(self.config(Path(out), f"on-{repeat}"), quiet,
                                         LiveViewer(server, render=False))
                        cpu["viewer, one browser"].append(time.process_time() - tic)
                        browser_cpu = tree_cpu_s(browser.service.process.pid) - browser_tic
                        clients = len(server.get_clients())
                finally:
                    server.stop()
                assert clients == 1, f"the browser was not connected at the end of the run ({clients} clients)"
                times["viewer, one browser"].append(summary.wall_time_s)
                print(f"pair {repeat}: " + ", ".join(f"{k} {times[k][-1]:.2f} s (CPU {cpu[k][-1]:.2f} s)"
                                                     for k in times) + f"; the browser's CPU {browser_cpu:.2f} s",
                      flush=True)
        for name, values in (("inversion wall time", times), ("process CPU time", cpu)):
            off, on = (statistics.median(v) for v in values.values())
            print(f"{name}: median without viewer {off:.2f} s, with the viewer and one browser {on:.2f} s, "
                  f"ratio {on / off:.3f}")


if __name__ == "__main__":
    tyro.cli(Overhead).main()
