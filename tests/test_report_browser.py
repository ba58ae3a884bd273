"""``report.html`` of a real short inversion, opened from disk in a real headless Chromium: every image
loads (none broken) and every table is there with its rows, as a user opening the page sees it."""

import io
import re
from pathlib import Path

import pytest
from browser import chromium
from rich.console import Console

from nerfinv_plugin.cli.invert import invert
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.settings import InvertConfig, StartConfig
from nerfinv_plugin.inversion.tracker import MonteCarloConfig
from nerfinv_plugin.report.build import REPORT_HTML
from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.trajectories import TrajectorySpec
from nerfinv_plugin.viewer.live import LiveViewer, start_server

FIGURES = {"error_vs_time.png", "loss_error_per_iteration.png", "error_per_frame.png", "overlays.png",
           "filmstrip.png"}
"""Figures a run with ground truth has when its model and sequence are where config.yml says (at least)."""

IMAGES = "return [...document.images].map(i => [i.getAttribute('src'), i.complete, i.naturalWidth])"
TABLES = "return [...document.querySelectorAll('table')].map(t => [t.rows.length, t.offsetHeight])"


@pytest.fixture(scope="module")
def report(toy_run, tmp_path_factory) -> Path:
    """report.html of a 2-frame inversion of the toy model, written by ns-invert's own code; the run has a
    live viewer that no browser ever connects to, and finishes all the same."""
    out = tmp_path_factory.mktemp("report-browser")
    write_shirt_trajectories(out, "toy", [TrajectorySpec(kind="roe1", num_frames=2, range_m=5.0)],
                             speedplus_like_camera(80, 50), False, seed=0, spp=16, step=lambda: None)
    config = InvertConfig(
        load_config=toy_run[0], sequence=str(out / "shirt" / "roe1"), output_dir=out, name="e", timestamp="t",
        device="cpu", target=(0.0, 0.0, 0.15), pixels=64, eval_pixels=256,
        starts=StartConfig(source="truth-offset", count=4, min_deg=10.0, max_deg=15.0, shift_m=0.1),
        optimizer=OptimizerConfig(iterations=8), monte_carlo=MonteCarloConfig(keep=(2, 1), spawn=1))
    server = start_server(None)
    try:
        summary = invert(config, Console(file=io.StringIO()), LiveViewer(server))
        assert summary.complete and not server.get_clients()
    finally:
        server.stop()
    return out / "e" / "nerfinv" / "t" / REPORT_HTML


def test_every_image_and_table_of_the_report_shows_in_a_browser(report):
    html = report.read_text()
    with chromium() as browser:
        browser.get(report.as_uri())
        images = browser.execute_script(IMAGES)
        tables = browser.execute_script(TABLES)
    assert sorted(src for src, _, _ in images) == sorted(re.findall(r'<img src="([^"]+)"', html)), images
    assert FIGURES <= {Path(src).name for src, _, _ in images}, images
    broken = [src for src, complete, width in images if not complete or width == 0]
    assert not broken, broken
    assert len(tables) == html.count("<table") and len(tables) >= 3, tables
    assert all(rows >= 2 and height > 0 for rows, height in tables), tables  # a header and rows, on screen


def test_a_broken_image_is_seen_as_broken(report, tmp_path):
    """The check above can fail: the same page with one figure's file missing shows it broken."""
    page = tmp_path / REPORT_HTML
    page.write_text(re.sub(r'src="([^"]*overlays\.png)"', r'src="missing/overlays.png"', report.read_text()))
    html = page.read_text().replace('src="report/', f'src="{report.parent.as_uri()}/report/')
    page.write_text(html)
    with chromium() as browser:
        browser.get(page.as_uri())
        images = browser.execute_script(IMAGES)
    widths = {Path(src).name: width for src, _, width in images}
    assert widths["overlays.png"] == 0 and all(widths[name] > 0 for name in FIGURES - {"overlays.png"}), widths
