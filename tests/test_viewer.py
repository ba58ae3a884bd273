"""The viewer of an inversion in a real headless Chromium (SwiftShader WebGL): a short inversion on the toy
model drawn live while a browser watches and then leaves, the scene nodes the server holds, the 3D canvas
of a browser that connects afterwards really drawn, the candidate trail the run folder keeps, and its
replay by ``ns-invert-view``."""

import io
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from browser import chromium, element_pixels
from rich.console import Console
from selenium.webdriver.common.by import By

from nerfinv_plugin.cli.invert import Invert, invert
from nerfinv_plugin.cli.view import RULES as VIEW_RULES
from nerfinv_plugin.cli.view import View
from nerfinv_plugin.cli.view import entrypoint as view_entrypoint
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.settings import InvertConfig, StartConfig
from nerfinv_plugin.inversion.tracker import MonteCarloConfig
from nerfinv_plugin.inversion.validation import INVERT_RULES, SettingsError, check, uncovered
from nerfinv_plugin.results.folder import RunFolder
from nerfinv_plugin.results.trail import TRAIL, poses_to_rows, read_scene, read_trail, rows_to_poses
from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.trajectories import TrajectorySpec
from nerfinv_plugin.viewer.live import LiveViewer, start_server
from nerfinv_plugin.viewer.replay import Replay
from nerfinv_plugin.viewer.scene import loss_colours

FRAMES = 3


@pytest.fixture(scope="module")
def shirt(toy_run, tmp_path_factory) -> Path:
    """A SHIRT root with a 3-frame roe1 trajectory of the toy scene at the model's resolution."""
    out = tmp_path_factory.mktemp("viewer")
    write_shirt_trajectories(out, "toy", [TrajectorySpec(kind="roe1", num_frames=FRAMES, range_m=5.0)],
                             speedplus_like_camera(80, 50), False, seed=0, spp=16, step=lambda: None)
    return out / "shirt"


def _config(toy_run, shirt: Path, out: Path) -> InvertConfig:
    """6 candidates 15-20 degrees off the first frame, 15 iterations a step, keep 2 then 1."""
    return InvertConfig(
        load_config=toy_run[0], sequence=str(shirt / "roe1"), output_dir=out, name="e", timestamp="t",
        device="cpu", target=(0.0, 0.0, 0.15), pixels=128, eval_pixels=512,
        starts=StartConfig(source="truth-offset", count=6, min_deg=15.0, max_deg=20.0, shift_m=0.25),
        optimizer=OptimizerConfig(iterations=15), monte_carlo=MonteCarloConfig(keep=(2, 1), spawn=2))


def _scene_nodes(server) -> dict[str, object]:
    """The scene nodes the server holds for the next browser that connects: the message that made each
    node, by name, unless a later message removed it (viser keeps the newest message of each kind and name,
    so this is the scene as a new browser gets it)."""
    buffer = dict(server._websock_server._broadcast_buffer.message_from_id)  # viser 0.2.7: no public accessor
    nodes = {}
    for key in sorted(buffer):
        message, kind = buffer[key], type(buffer[key]).__name__
        name = getattr(message, "name", None)
        if name is None or kind.startswith("Set"):  # poses and visibility of nodes made before
            continue
        if kind == "RemoveSceneNodeMessage":
            nodes.pop(name, None)
        else:
            nodes[name] = message
    return nodes


def _wait(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"waited {seconds} s for {what}")
        time.sleep(0.1)


def _canvas(browser):
    """The largest canvas of the page: three.js' 3D view."""
    _wait(lambda: browser.find_elements(By.TAG_NAME, "canvas"), 60, "the viewer's canvas")
    return max(browser.find_elements(By.TAG_NAME, "canvas"), key=lambda c: c.size["width"] * c.size["height"])


@pytest.fixture(scope="module")
def watched(toy_run, shirt, tmp_path_factory):
    """A short inversion drawn live: a browser watches from the start and leaves after the first step; the
    run goes on. Yields (run folder, server, viewer) with the server still up."""
    out = tmp_path_factory.mktemp("watched")
    server = start_server(None)
    viewer = LiveViewer(server)
    errors: list[BaseException] = []

    def run() -> None:
        try:
            invert(_config(toy_run, shirt, out), Console(file=io.StringIO()), viewer)
        except BaseException as err:  # the test thread reports it
            errors.append(err)

    folder = out / "e" / "nerfinv" / "t"
    thread = threading.Thread(target=run)
    with chromium() as browser:
        browser.get(f"http://localhost:{server.get_port()}")
        _wait(lambda: len(server.get_clients()) == 1, 60, "the browser's websocket")
        thread.start()
        _wait(lambda: (folder / TRAIL).is_file() or not thread.is_alive(), 120, "the first step")
    _wait(lambda: len(server.get_clients()) == 0, 30, "the browser to disconnect")
    thread.join(300)
    assert not thread.is_alive() and not errors, errors
    yield folder, server, viewer
    server.stop()


def test_the_run_goes_on_after_the_browser_leaves_and_the_server_holds_the_scene(watched):
    folder, server, _ = watched
    rows, steps = RunFolder(folder).rows(), RunFolder(folder).steps()
    assert [r.index for r in rows] == list(range(FRAMES)) and RunFolder(folder).summary() is not None
    nodes = _scene_nodes(server)
    candidates = sorted(n for n in nodes if n.startswith("/candidates/"))
    kept = sorted(n for n in nodes if n.startswith("/kept/"))
    assert candidates == [f"/candidates/{k:03d}" for k in range(steps[-1].candidates)], candidates
    assert kept == [f"/kept/{k:03d}" for k in range(steps[-1].kept)], kept
    assert "/observed" in nodes and nodes["/observed"].image_binary is not None  # the frame's image on it
    training = [n for n in nodes if n.startswith("/cameras/camera_")]
    assert len(training) == 60, len(training)  # the toy model's 60 training views
    assert {"/trajectory/estimate/points", "/trajectory/estimate/line", "/trajectory/truth/points",
            "/trajectory/truth/line"} <= set(nodes)
    assert len(nodes["/trajectory/estimate/points"].points) == FRAMES
    # The estimated trajectory is the run's estimates, at nerfstudio's viewer scale.
    estimates = np.array([np.asarray(r.c2w_model)[:3, 3] for r in rows]) * 10.0
    np.testing.assert_allclose(nodes["/trajectory/estimate/points"].points, estimates, atol=1e-4)


def test_a_browser_that_connects_later_draws_the_scene_and_shows_both_images(watched):
    folder, server, viewer = watched
    inversion = [*viewer.scene.candidates.values(), *viewer.scene.kept.values()]
    with chromium() as browser:
        browser.get(f"http://localhost:{server.get_port()}")
        _wait(lambda: len(server.get_clients()) == 1, 60, "the browser's websocket")
        canvas = _canvas(browser)
        _wait(lambda: len(browser.find_elements(By.CSS_SELECTOR, "img[alt='model at the best candidate']")) == 1,
              60, "the panel's images")
        time.sleep(3.0)  # SwiftShader draws a few frames a second
        shown = element_pixels(canvas).astype(np.int16)
        images = browser.execute_script(
            "return [...document.querySelectorAll('img')].map(i => [i.alt, i.complete, i.naturalWidth])")
        for handle in inversion:
            handle.visible = False
        time.sleep(3.0)
        hidden = element_pixels(canvas).astype(np.int16)
    for handle in inversion:
        handle.visible = True
    assert shown.shape[0] > 100 and shown.shape[1] > 100, shown.shape
    # Not blank: a canvas of one colour (nothing drawn, or WebGL missing) has no spread.
    assert shown.reshape(-1, 3).std(0).max() > 10, shown.reshape(-1, 3).std(0)
    # And what it draws is the inversion: hiding the candidates' frustums changes a good part of it.
    changed = (np.abs(shown - hidden).max(2) > 40).mean()
    assert changed > 0.002, changed
    widths = {alt: width for alt, complete, width in images if alt in ("observed", "model at the best candidate")}
    assert widths.get("observed", 0) > 0 and widths.get("model at the best candidate", 0) > 0, images


def test_the_trail_holds_every_step_and_replays(watched, tmp_path):
    folder, _, _ = watched
    steps, offset = read_trail(folder)
    rows = RunFolder(folder).steps()
    assert [s.step for s in steps] == [r.step for r in rows]
    for step, row in zip(steps, rows):
        assert len(step.final) == row.candidates and len(step.kept) == row.kept
        assert step.iterations == [0, 5, 10, 14]  # every 5 iterations and the last of 15
        assert np.argmin(step.final_losses) == step.kept[0]  # the best candidate is kept first
        assert all(p.shape == (row.candidates, 4, 4) for p in step.poses)
    # The last step's best final pose is the frame's estimate.
    np.testing.assert_allclose(steps[-1].final[steps[-1].kept[0]], RunFolder(folder).rows()[-1].c2w_model,
                               atol=1e-4)
    scene = read_scene(folder)
    assert scene.frames == [r.name for r in RunFolder(folder).rows()] and all(t is not None for t in scene.truths)
    # A line still being written (no newline yet) is not read; it is, once finished.
    trail = folder / TRAIL
    with open(trail, "ab") as f:
        f.write(b'{"step": 99')
    assert read_trail(folder, offset) == ([], offset)
    server = start_server(None)
    try:
        replay = Replay.open(folder, server, interval_s=0.0, render=True)
        assert replay.play_new() == len(steps) and replay.complete()
        # viser files each message into its buffer from its own event loop: under load the last may lag
        _wait(lambda: len(_scene_nodes(server)["/trajectory/estimate/points"].points) == FRAMES, 10,
              "the whole estimated trajectory in the scene")
        nodes = _scene_nodes(server)
        assert len([n for n in nodes if n.startswith("/kept/")]) == rows[-1].kept
    finally:
        server.stop()


def test_poses_round_trip_through_the_trail_rows():
    torch.manual_seed(0)
    from nerfinv_plugin.geometry.se3 import exp_se3

    poses = exp_se3(torch.randn(5, 6, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(rows_to_poses(poses_to_rows(poses)), poses, atol=5e-5)


def test_losses_colour_green_to_red_and_grey_when_dropped():
    colours = loss_colours(np.array([0.001, 0.1, np.inf, 0.01]))
    best, worst, dropped = colours[0], colours[1], colours[2]
    assert best[1] > best[0] and worst[0] > worst[1] and dropped[0] == dropped[1] == dropped[2]


def test_view_on_a_folder_that_is_not_a_run_exits_2_with_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["ns-invert-view", str(tmp_path), "--port", "0"])
    with pytest.raises(SystemExit) as exit_info:
        view_entrypoint()
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and "\n" not in err and "--port must be a whole number from 1 to 65535" in err
    monkeypatch.setattr(sys, "argv", ["ns-invert-view", str(tmp_path), "--no-render"])
    with pytest.raises(SystemExit) as exit_info:
        view_entrypoint()
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and "\n" not in err and "not an ns-invert run folder" in err, err


def test_every_numeric_option_of_the_viewer_commands_has_a_rule():
    assert uncovered(Invert, INVERT_RULES) == []  # --viewer-port among them
    assert uncovered(View, VIEW_RULES) == []
    with pytest.raises(SettingsError, match="^--viewer-port must be a whole number from 1 to 65535"):
        check(Invert(viewer_port=70000), INVERT_RULES)
    check(Invert(viewer_port=7007), INVERT_RULES)
