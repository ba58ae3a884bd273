"""``ns-invert-bench viewer``: a real pair of toy inversions, without and with the viewer while the headless
Chromium watches, and the command's refusals (a missing browser before any run, bad options)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nerfinv_plugin.bench import viewer_overhead as overhead_module
from nerfinv_plugin.bench.viewer_overhead import OverheadPair, ViewerOverhead, viewer_overhead
from nerfinv_plugin.cli.bench import VIEWER_RULES, ViewerBench, entrypoint
from nerfinv_plugin.inversion.validation import uncovered
from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.trajectories import TrajectorySpec
from nerfinv_plugin.viewer import browser
from nerfinv_plugin.viewer.browser import BrowserError, find_chromium


def test_a_pair_is_measured_with_the_browser_connected_and_drawing(toy_run, tmp_path):
    write_shirt_trajectories(tmp_path, "toy", [TrajectorySpec(kind="roe1", num_frames=1, range_m=5.0)],
                             speedplus_like_camera(80, 50), False, seed=0, spp=16, step=lambda: None)
    heard: list[OverheadPair] = []
    measured = viewer_overhead(toy_run[0], str(tmp_path / "shirt" / "roe1"), (0.0, 0.0, 0.15), stop=1,
                               iterations=3, repeats=1, on_pair=heard.append)
    assert heard == measured.pairs and len(heard) == 1
    pair = heard[0]
    assert pair.wall_off_s > 0 and pair.wall_on_s > 0 and pair.cpu_off_s > 0 and pair.cpu_on_s > 0, pair
    assert pair.browser_cpu_s > 0, pair  # chromedriver alone idles: this is the browser's own processes
    assert measured.medians(wall=True) == (pair.wall_off_s, pair.wall_on_s)


def test_idle_priority_reaches_every_thread_of_the_tree_and_what_it_starts_later(tmp_path):
    """``--browser-priority idle`` must reach chromium's renderer and GPU processes, which chromedriver starts
    through chromium, and each of their threads (Linux schedules threads, not processes): here a process
    whose child runs a second thread, then starts a grandchild once the change is made."""
    go = tmp_path / "go"
    inner = ("import os, subprocess, sys, threading, time\n"
             "threading.Thread(target=time.sleep, args=(30,), daemon=True).start()\n"
             f"while not os.path.exists({str(go)!r}): time.sleep(0.02)\n"
             "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)']); time.sleep(30)")
    outer = subprocess.Popen([sys.executable, "-c",
                              f"import subprocess, sys; subprocess.run([sys.executable, '-c', {inner!r}])"])

    def tree() -> set[int]:
        return overhead_module._tree(outer.pid, overhead_module._process_stats())

    def wait_for(processes: int) -> None:
        deadline = time.monotonic() + 20
        while len(tree()) < processes:
            assert time.monotonic() < deadline, f"the process tree did not reach {processes} processes"
            time.sleep(0.02)

    try:
        wait_for(2)
        time.sleep(0.5)  # the child's second thread
        assert overhead_module.idle_tree(outer.pid) >= 3
        go.touch()
        wait_for(3)
        threads = [int(t.name) for pid in tree() for t in Path(f"/proc/{pid}/task").iterdir()]
        assert len(threads) >= 4, threads
        assert all(os.sched_getscheduler(tid) == os.SCHED_IDLE for tid in threads), threads
        assert os.sched_getscheduler(0) != os.SCHED_IDLE  # not the caller
    finally:
        for pid in tree() - {outer.pid}:
            os.kill(pid, signal.SIGKILL)
        outer.kill()
        outer.wait()


def test_medians_are_taken_per_column():
    pairs = [OverheadPair(1.0, 2.0, 10.0, 20.0, 0.5), OverheadPair(3.0, 5.0, 30.0, 40.0, 0.5),
             OverheadPair(2.0, 9.0, 50.0, 60.0, 0.5)]
    assert ViewerOverhead(pairs).medians(wall=True) == (2.0, 5.0)
    assert ViewerOverhead(pairs).medians(wall=False) == (30.0, 40.0)


def test_a_missing_browser_or_selenium_is_named_with_its_fix(monkeypatch):
    monkeypatch.setattr(browser.shutil, "which", lambda name: None if name == "chromedriver" else f"/usr/bin/{name}")
    with pytest.raises(BrowserError, match="apt-get install -y chromium chromium-driver"):
        find_chromium()
    monkeypatch.setitem(sys.modules, "selenium", None)  # import selenium raises ImportError
    with pytest.raises(BrowserError, match=r"pip install 'nerfinv\[test\]'"):
        find_chromium()


def _refused(monkeypatch, capsys, *args: str) -> str:
    """Run ``ns-invert-bench viewer ARGS`` in this process, where no inversion may start; its one-line error."""
    def no_run(*args, **kwargs):
        raise AssertionError("an inversion ran")

    monkeypatch.setattr(overhead_module, "invert", no_run)
    monkeypatch.setattr(sys, "argv", ["ns-invert-bench", "viewer", *args])
    with pytest.raises(SystemExit) as exit_info:
        entrypoint()
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and len(err.strip().splitlines()) == 1, err
    return err


def test_the_command_refuses_before_any_run(monkeypatch, capsys, tmp_path: Path):
    assert uncovered(ViewerBench, VIEWER_RULES) == []
    base = ["--load-config", str(tmp_path / "config.yml"), "--sequence", str(tmp_path)]
    assert "--repeats must be a whole number of at least 1, not 0" in _refused(monkeypatch, capsys, *base,
                                                                               "--repeats", "0")
    assert "--stop must be" in _refused(monkeypatch, capsys, *base, "--stop", "0")
    assert "--target must be" in _refused(monkeypatch, capsys, *base, "--target", "0", "nan", "0")
    monkeypatch.setattr(browser.shutil, "which", lambda name: None)
    assert "chromium and chromium-driver are needed" in _refused(monkeypatch, capsys, *base)
