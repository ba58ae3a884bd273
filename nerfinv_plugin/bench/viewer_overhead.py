"""What ``ns-invert --viewer`` costs an inversion: the same run without the viewer and with it (model render
off) while one headless Chromium (SwiftShader WebGL, as the browser tests) watches, alternated so that a
change in the machine's load falls on both. Each pair records the runs' inversion times (the run's own
``wall_time_s``: model loading and the report are not counted), the CPU time of this process over the whole
``invert`` call (all its threads, viser's among them; loading and the report are the same in both, so the
difference is the viewer's own work, which a busy machine's load does not blur), and the CPU time the
browser's processes took meanwhile (software WebGL on the same cores).

A browser on the user's own machine, or drawing with a GPU, takes nothing from the run; here it draws
viser's canvas in software on the run's two cores, which measures the browser rather than the viewer
(docs/benchmarks.md: 3.7x). ``browser_priority="idle"`` puts every thread of the browser's processes under
Linux's ``SCHED_IDLE`` once it is connected: it runs only on the time the inversion leaves, which stands in
for a browser elsewhere while it still holds the real websocket and receives every message the viewer sends."""

import io
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rich.console import Console

from nerfinv_plugin.cli.invert import invert
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.settings import InvertConfig, StartConfig
from nerfinv_plugin.inversion.tracker import MonteCarloConfig
from nerfinv_plugin.inversion.validation import validate
from nerfinv_plugin.viewer.browser import BrowserError, chromium, find_chromium
from nerfinv_plugin.viewer.live import LiveViewer, start_server

CONNECT_S = 60.0
"""How long the browser may take to open the viewer's websocket."""


BrowserPriority = Literal["normal", "idle"]
"""normal: the browser competes with the run for the cores; idle: it runs only when the cores are idle."""


def _process_stats() -> dict[int, tuple[int, float]]:
    """Every live process: its parent and its CPU seconds (user + system), from Linux ``/proc``."""
    stats = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:  # the process ended meanwhile
                continue
            stats[int(entry.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"))
    return stats


def _tree(root: int, stats: dict[int, tuple[int, float]]) -> set[int]:
    """``root`` and every live process under it."""
    under = {root}
    for _ in range(8):  # chromedriver -> chromium -> its zygote, renderer and GPU processes
        under |= {pid for pid, (parent, _) in stats.items() if parent in under}
    return under


def tree_cpu_s(root: int) -> float:
    """CPU seconds (user + system) of every live process under ``root``."""
    stats = _process_stats()
    return sum(stats.get(pid, (0, 0.0))[1] for pid in _tree(root, stats))


def idle_tree(root: int) -> int:
    """Put every thread of every process under ``root`` under ``SCHED_IDLE`` (threads and processes they start
    later inherit it); returns how many threads were changed. A thread that ended meanwhile is skipped."""
    changed = 0
    for pid in _tree(root, _process_stats()):
        try:
            threads = [int(t.name) for t in Path(f"/proc/{pid}/task").iterdir()]
        except OSError:
            continue
        for tid in threads:
            try:
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
                changed += 1
            except (ProcessLookupError, PermissionError):
                continue
    return changed


@dataclass(frozen=True)
class OverheadPair:
    """One run without the viewer and the next one with it and a browser watching."""

    wall_off_s: float
    """Inversion wall time without the viewer (the run's ``wall_time_s``)."""
    wall_on_s: float
    """Inversion wall time with the viewer and one browser."""
    cpu_off_s: float
    """CPU time of this process over the ``invert`` call without the viewer."""
    cpu_on_s: float
    """CPU time of this process over the ``invert`` call with the viewer."""
    browser_cpu_s: float
    """CPU time of the browser's processes during the viewed run."""


@dataclass(frozen=True)
class ViewerOverhead:
    """All pairs of a measurement, and their medians."""

    pairs: list[OverheadPair]

    def medians(self, wall: bool) -> tuple[float, float]:
        """Median (without, with the viewer) of the inversion wall times, or of the process CPU times."""
        off = [p.wall_off_s if wall else p.cpu_off_s for p in self.pairs]
        on = [p.wall_on_s if wall else p.cpu_on_s for p in self.pairs]
        return statistics.median(off), statistics.median(on)


def overhead_config(load_config: Path, sequence: str, target: tuple[float, float, float], stop: int,
                    iterations: int, out: Path, timestamp: str) -> InvertConfig:
    """The runs' settings: a small inversion on the CPU, 6 starts turned 15-20 deg off the true attitude,
    128 pixels, keeping 2 then 1 candidates with 2 spawned."""
    config = InvertConfig(load_config=load_config, sequence=sequence, output_dir=out, name="overhead",
                          timestamp=timestamp, device="cpu", target=target, stop=stop, pixels=128, eval_pixels=512,
                          starts=StartConfig(source="truth-offset", count=6, min_deg=15.0, max_deg=20.0, shift_m=0.25),
                          optimizer=OptimizerConfig(iterations=iterations),
                          monte_carlo=MonteCarloConfig(keep=(2, 1), spawn=2))
    validate(config)
    return config


def viewer_overhead(load_config: Path, sequence: str, target: tuple[float, float, float], stop: int,
                    iterations: int, repeats: int,
                    on_pair: Callable[[OverheadPair], None] = lambda pair: None,
                    browser_priority: BrowserPriority = "normal") -> ViewerOverhead:
    """Run ``repeats`` pairs (without, then with the viewer and one browser at ``browser_priority``), in a
    temporary folder that is removed afterwards; ``on_pair`` hears each pair as it finishes. Raises
    :class:`BrowserError` when no browser can be started (before the first run) or it is not connected for the
    whole viewed run."""
    find_chromium()
    quiet = Console(file=io.StringIO())
    pairs = []
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        for repeat in range(repeats):
            tic = time.process_time()
            off = invert(overhead_config(load_config, sequence, target, stop, iterations, out, f"off-{repeat}"), quiet)
            cpu_off = time.process_time() - tic
            server = start_server(None)
            try:
                with chromium() as browser:
                    browser.get(f"http://localhost:{server.get_port()}")
                    deadline = time.monotonic() + CONNECT_S
                    while not server.get_clients():
                        if time.monotonic() > deadline:
                            raise BrowserError(f"chromium did not open the viewer's websocket in {CONNECT_S:g} s")
                        time.sleep(0.1)
                    pid = browser.service.process.pid
                    if browser_priority == "idle" and not idle_tree(pid):
                        raise BrowserError("could not put the browser's threads under SCHED_IDLE")
                    tic, browser_tic = time.process_time(), tree_cpu_s(pid)
                    on = invert(overhead_config(load_config, sequence, target, stop, iterations, out, f"on-{repeat}"),
                                quiet, LiveViewer(server, render=False))
                    cpu_on = time.process_time() - tic
                    browser_cpu = tree_cpu_s(pid) - browser_tic
                    clients = len(server.get_clients())
            finally:
                server.stop()
            if clients != 1:
                raise BrowserError(f"the browser was not connected at the end of the viewed run ({clients} clients)")
            pairs.append(OverheadPair(off.wall_time_s, on.wall_time_s, cpu_off, cpu_on, browser_cpu))
            on_pair(pairs[-1])
    return ViewerOverhead(pairs)
