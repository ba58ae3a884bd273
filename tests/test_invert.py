"""``ns-invert`` end to end on the tiny toy model: results files, errors, resuming, Ctrl-C, bad input,
presets, and the demo's reuse of finished stages."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro

from nerfinv_plugin.cli.demo import Demo
from nerfinv_plugin.cli.invert import Invert, entrypoint
from nerfinv_plugin.demo import render_data, train_model
from nerfinv_plugin.inversion.optimizer import IterationRecord, OptimizerConfig
from nerfinv_plugin.inversion.session import Events, Inversion
from nerfinv_plugin.inversion.settings import (
    InvertConfig,
    RenderConfig,
    StartConfig,
    defaults_with_preset,
    presets_dir,
    read_config,
    to_dict,
    write_config,
)
from nerfinv_plugin.inversion.tracker import MonteCarloConfig
from nerfinv_plugin.results.folder import CSV_COLUMNS, RunFolder
from nerfinv_plugin.synth.datasets import TrainingSetSpec, speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.trajectories import TrajectorySpec


@pytest.fixture(scope="module")
def shirt(toy_run, tmp_path_factory) -> Path:
    """A SHIRT root with a 4-frame roe1 trajectory of the toy scene at the model's resolution."""
    out = tmp_path_factory.mktemp("invert")
    write_shirt_trajectories(out, "toy", [TrajectorySpec(kind="roe1", num_frames=4, range_m=5.0)],
                             speedplus_like_camera(80, 50), False, seed=0, spp=32, step=lambda: None)
    return out / "shirt"


def _config(toy_run, shirt: Path, out: Path, **changes) -> InvertConfig:
    """A small, quick inversion: 6 candidates 15-20 degrees off the first frame, keep 2 then 1."""
    config = InvertConfig(
        load_config=toy_run[0], sequence=str(shirt / "roe1"), output_dir=out, name="e", timestamp="t",
        device="cpu", target=(0.0, 0.0, 0.15), pixels=128, eval_pixels=512,
        starts=StartConfig(source="truth-offset", count=6, min_deg=15.0, max_deg=20.0, shift_m=0.25),
        optimizer=OptimizerConfig(iterations=25), monte_carlo=MonteCarloConfig(keep=(2, 1), spawn=2))
    return replace(config, **changes)


def _cli(argv: list[str], monkeypatch, capsys) -> tuple[int, str]:
    """Run ``ns-invert`` in this process; return its exit code and stderr."""
    monkeypatch.setattr(sys, "argv", ["ns-invert", *argv])
    with pytest.raises(SystemExit) as exit_info:
        entrypoint()
    return exit_info.value.code, capsys.readouterr().err


def test_cli_end_to_end_writes_results_that_track_the_target(toy_run, shirt, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [
        "ns-invert", "--load-config", str(toy_run[0]), "--sequence", str(shirt / "roe1"), "--stop", "3",
        "--output-dir", str(tmp_path), "--name", "e", "--timestamp", "t", "--device", "cpu",
        "--target", "0", "0", "0.15", "--starts.source", "truth-offset", "--starts.count", "6",
        "--optimizer.iterations", "25", "--monte-carlo.keep", "2", "1", "--pixels", "128", "--eval-pixels", "512"])
    entrypoint()
    run = tmp_path / "e" / "nerfinv" / "t"
    rows = RunFolder(run).rows()
    assert [r.frame for r in rows] == [0, 1, 2] and [r.candidates for r in rows] == [6, 6, 3]
    errors = np.array([r.rotation_deg for r in rows])
    assert np.isfinite(errors).all()
    assert errors.min() < 8.0 and errors[-1] < 12.0, errors  # starts were 15-20 degrees off
    assert all(r.translation_m < 0.5 for r in rows)
    csv_lines = (run / "results.csv").read_text().splitlines()
    assert csv_lines[0].split(",") == list(CSV_COLUMNS) and len(csv_lines) == 4
    summary = json.loads((run / "summary.json").read_text())
    assert summary["complete"] and summary["frames_done"] == 3
    assert summary["rotation_deg"]["mean"] == pytest.approx(errors.mean())
    assert read_config(run / "config.yml") == _config(toy_run, shirt, tmp_path, stop=3, device="cpu")
    steps = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
    assert len(steps) == 3 and len(steps[0]["best_loss_per_iteration"]) == 25
    out = capsys.readouterr().out
    assert "frame 2 (img000003.jpg): rotation" in out
    assert (run / "report.html").is_file() and (run / "report" / "overlays.png").is_file() and "report:" in out


def test_estimate_in_the_dataset_frame_matches_the_model_frame_pose(toy_run, shirt, tmp_path):
    """q, r written for SHIRT are the model-frame estimate taken back through the dataparser transform."""
    from nerfinv_plugin.geometry.frames import quat_wxyz_to_rotmat
    from nerfinv_plugin.model.loading import load_model

    config = _config(toy_run, shirt, tmp_path, stop=1, optimizer=OptimizerConfig(iterations=2))
    Inversion.create(config).run()
    row = RunFolder(tmp_path / "e" / "nerfinv" / "t").rows()[0]
    loaded = load_model(toy_run[0], device="cpu")
    c2w_gl = loaded.model_to_dataset(np.array(row.c2w_model))
    c2w_cv = c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0])
    # The label is the body in the camera frame: R = c2w_cv[:3, :3]^T, r = -R c2w_cv[:3, 3].
    np.testing.assert_allclose(quat_wxyz_to_rotmat(np.array(row.q)), c2w_cv[:3, :3].T, atol=1e-6)
    np.testing.assert_allclose(row.r, -c2w_cv[:3, :3].T @ c2w_cv[:3, 3], atol=1e-6)


def test_interrupted_and_resumed_run_equals_an_uninterrupted_one(toy_run, shirt, tmp_path):
    small = dict(stop=3, optimizer=OptimizerConfig(iterations=6), pixels=64, eval_pixels=256)
    Inversion.create(_config(toy_run, shirt, tmp_path, timestamp="whole", **small)).run()

    def stop_in_second_step(i: int, record: IterationRecord) -> None:
        if len(RunFolder(tmp_path / "e" / "nerfinv" / "cut").rows()) == 1 and i == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        Inversion.create(_config(toy_run, shirt, tmp_path, timestamp="cut", **small),
                         Events(iteration=stop_in_second_step)).run()
    cut = tmp_path / "e" / "nerfinv" / "cut"
    assert len(RunFolder(cut).rows()) == 1 and not (cut / "summary.json").exists()
    Inversion.resume(cut).run()
    whole, resumed = RunFolder(tmp_path / "e" / "nerfinv" / "whole").rows(), RunFolder(cut).rows()
    assert len(resumed) == 3
    for a, b in zip(whole, resumed):
        for key in ("q", "r", "c2w_model", "loss", "rotation_deg", "translation_m", "candidates"):
            assert getattr(a, key) == getattr(b, key), (key, getattr(a, key), getattr(b, key))


def test_ctrl_c_keeps_the_finished_frames_and_says_how_to_resume(toy_run, shirt, tmp_path):
    run = tmp_path / "e" / "nerfinv" / "t"
    args = ["--load-config", str(toy_run[0]), "--sequence", str(shirt / "roe1"), "--output-dir", str(tmp_path),
            "--name", "e", "--timestamp", "t", "--device", "cpu", "--starts.source", "truth-offset",
            "--starts.count", "2", "--optimizer.iterations", "3", "--pixels", "32", "--eval-pixels", "64"]
    # Each frame takes a fraction of a second here; steps-per-frame makes frames long enough to interrupt.
    # A shell that starts jobs in the background (CI) makes them ignore SIGINT, and Python then installs no
    # KeyboardInterrupt handler: give the command the disposition a terminal would.
    process = subprocess.Popen([shutil.which("ns-invert"), *args, "--steps-per-frame", "40"], text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "COLUMNS": "200"},
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 240
    while not RunFolder(run).rows() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.2)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert f"ns-invert --resume {run}" in err and len(err.strip().splitlines()) == 1, err
    rows = RunFolder(run).rows()
    assert 1 <= len(rows) < 4 and RunFolder(run).load() is not None
    assert Inversion.resume(run).config.steps_per_frame == 40


def test_a_candidate_that_turns_nan_is_dropped_with_a_message(toy_run, shirt, tmp_path, monkeypatch):
    original = Inversion._starts

    def with_a_nan(self, *args):
        start = original(self, *args)
        start[2, 0, 3] = float("nan")
        return start

    monkeypatch.setattr(Inversion, "_starts", with_a_nan)
    warnings = []
    config = _config(toy_run, shirt, tmp_path, stop=2, optimizer=OptimizerConfig(iterations=3))
    Inversion.create(config, Events(warn=warnings.append)).run()
    rows = RunFolder(tmp_path / "e" / "nerfinv" / "t").rows()
    assert len(rows) == 2 and rows[0].dropped == 1 and np.isfinite(rows[1].rotation_deg)
    assert len(warnings) == 1 and "dropped candidate(s) 2" in warnings[0]


def _copy_shirt(shirt: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "shirt"
    shutil.copytree(shirt, copy)
    return copy


def _not_a_config(tmp_path: Path) -> Path:
    (tmp_path / "config.yml").write_text("just: a mapping\n")
    return tmp_path / "config.yml"


def _unreadable_config(tmp_path: Path) -> Path:
    (tmp_path / "config.yml").write_text("!!python/object:nerfstudio.engine.trainer.TrainerConfig\n  a: [\n")
    return tmp_path / "config.yml"


def _folder_without_poses(shirt: Path, tmp_path: Path) -> Path:
    """The trajectory's images and camera.json in a plain folder: no ground truth."""
    folder = tmp_path / "images"
    shutil.copytree(shirt / "roe1" / "synthetic" / "images", folder)
    shutil.copy(shirt / "camera.json", folder)
    return folder


def _no_checkpoint(toy_run, tmp_path: Path) -> Path:
    shutil.copy(toy_run[0], tmp_path / "config.yml")
    return tmp_path / "config.yml"


def _missing_image(shirt: Path, tmp_path: Path) -> Path:
    copy = _copy_shirt(shirt, tmp_path)
    (copy / "roe1" / "synthetic" / "images" / "img000002.jpg").unlink()
    return copy


def _wrong_size(shirt: Path, tmp_path: Path) -> Path:
    copy = _copy_shirt(shirt, tmp_path)
    camera = json.loads((copy / "camera.json").read_text())
    (copy / "camera.json").write_text(json.dumps({**camera, "Nu": 160, "Nv": 100}))
    return copy


BAD_INPUTS = {
    "config missing": (lambda run, shirt, tmp: (tmp / "nowhere" / "config.yml", shirt / "roe1", []), "config.yml"),
    "not a nerfstudio config": (lambda run, shirt, tmp: (_not_a_config(tmp), shirt / "roe1", []), "nerfstudio"),
    "checkpoint missing": (lambda run, shirt, tmp: (_no_checkpoint(run, tmp), shirt / "roe1", []), "checkpoint"),
    "sequence missing": (lambda run, shirt, tmp: (run[0], tmp / "roe9", []), "does not exist"),
    "format not recognised": (lambda run, shirt, tmp: (run[0], tmp, []), "SHIRT"),
    "image missing": (lambda run, shirt, tmp: (run[0], _missing_image(shirt, tmp) / "roe1", []), "img000002.jpg"),
    "size mismatch": (lambda run, shirt, tmp: (run[0], _wrong_size(shirt, tmp) / "roe1", []), "160"),
    "empty sequence": (lambda run, shirt, tmp: (run[0], shirt / "roe1", ["--start", "10"]), "4 frames"),
    "config unreadable": (lambda run, shirt, tmp: (_unreadable_config(tmp), shirt / "roe1", []), "config.yml"),
    "truth needed": (lambda run, shirt, tmp: (run[0], _folder_without_poses(shirt, tmp),
                                              ["--starts.source", "truth-offset"]), "true pose"),
}


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_bad_input_gets_one_line_and_exit_code_2_and_writes_nothing(case, toy_run, shirt, tmp_path, monkeypatch,
                                                                    capsys):
    make, expected = BAD_INPUTS[case]
    config, sequence, extra = make(toy_run, shirt, tmp_path)
    out = tmp_path / "outputs"
    code, err = _cli(["--load-config", str(config), "--sequence", str(sequence), "--output-dir", str(out),
                      "--device", "cpu", *extra], monkeypatch, capsys)
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("ns-invert: "), err
    assert expected in err, err
    assert not out.exists()  # nothing half-made


def test_missing_required_options_and_unknown_preset(monkeypatch, capsys):
    code, err = _cli([], monkeypatch, capsys)
    assert code == 2 and "--load-config" in err and "--resume" in err
    code, err = _cli(["--preset", "no-such-preset"], monkeypatch, capsys)
    assert code == 2 and "shirt-synthetic" in err and len(err.strip().splitlines()) == 1


def test_every_preset_loads_and_the_command_line_overrides_it(tmp_path):
    names = sorted(p.stem for p in presets_dir().glob("*.yml"))
    assert {"toy", "shirt-synthetic", "shirt-lightbox", "far-starts"} <= set(names)
    for name in names:
        config = defaults_with_preset(["--preset", name])
        assert config.preset == name and config != InvertConfig(preset=name)
    far = defaults_with_preset(["--preset", "far-starts"])
    assert far.starts.source == "volume" and far.starts.count == 80 and far.optimizer.iterations == 512
    assert far.monte_carlo.keep_fraction == 0.25
    default = Invert(**{k: getattr(far, k) for k in far.__dataclass_fields__})
    parsed = tyro.cli(Invert, default=default, args=["--starts.count", "12", "--load-config", "c.yml"])
    assert parsed.starts.count == 12 and parsed.starts.max_range_m == 9.0 and parsed.optimizer.iterations == 512
    write_config(tmp_path / "c.yml", parsed)
    assert to_dict(read_config(tmp_path / "c.yml")) == to_dict(parsed)


def test_resuming_a_folder_that_is_not_a_run_says_so(tmp_path, monkeypatch, capsys):
    code, err = _cli(["--resume", str(tmp_path)], monkeypatch, capsys)
    assert code == 2 and "not an ns-invert run folder" in err


PLUMBING_STARTS = StartConfig(source="truth-offset", count=4)
"""A model trained for 30 iterations has learned nothing a view bank could match, nor a density to read
the object's size from: the demo's stage reuse is tested with starts placed from the truth and a given
radius (the bare path is tested in test_pose_from_nothing.py)."""


def test_demo_runs_every_stage_once_and_reuses_them(tmp_path, monkeypatch, capsys):
    demo = Demo(data_dir=tmp_path / "data", output_dir=tmp_path / "outputs", frames=2, training_iterations=30,
                iterations=3, device="cpu", training_set=TrainingSetSpec(8, 1, 1, 40, 25), starts=PLUMBING_STARTS,
                render=RenderConfig(target_radius_m=1.0))
    demo.main()
    run = demo.run_dir
    rows = RunFolder(run).rows()
    assert len(rows) == 2 and json.loads((run / "summary.json").read_text())["complete"]
    first = capsys.readouterr().out
    assert "already" not in first
    stamps = {p: p.stat().st_mtime_ns for p in [demo.data_dir / "transforms.json", demo.model_config,
                                                run / "results.jsonl"]}
    demo.main()
    second = capsys.readouterr().out
    assert second.count("already") == 3, second
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items())


def test_interrupted_demo_inversion_continues(tmp_path):
    """An interrupted demo inversion leaves a run folder; the next demo resumes it instead of refusing."""
    demo = Demo(data_dir=tmp_path / "data", output_dir=tmp_path / "outputs", frames=2, training_iterations=30,
                iterations=3, device="cpu", training_set=TrainingSetSpec(8, 1, 1, 40, 25), starts=PLUMBING_STARTS,
                render=RenderConfig(target_radius_m=1.0))
    render_data(demo, lambda: None)
    train_model(demo)

    def stop_after_first_frame(i: int, record: IterationRecord) -> None:
        if RunFolder(demo.run_dir).rows():
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        Inversion.create(demo.inversion(), Events(iteration=stop_after_first_frame)).run()
    assert len(RunFolder(demo.run_dir).rows()) == 1
    demo.main()
    rows = RunFolder(demo.run_dir).rows()
    assert len(rows) == 2 and np.isfinite([r.rotation_deg for r in rows]).all()


def test_prior_starts_surround_the_given_label_and_need_one(toy_run, shirt, tmp_path):
    from nerfinv_plugin.data.sequences import read_sequence
    from nerfinv_plugin.geometry.se3 import geodesic_deg
    from nerfinv_plugin.inversion.session import InversionError
    from nerfinv_plugin.model.loading import load_model

    label = json.loads((shirt / "roe1" / "roe1.json").read_text())[0]
    starts = StartConfig(source="prior", count=6, max_deg=10.0, shift_m=0.1,
                         prior_q=tuple(label["q_vbs2tango_true"]), prior_r=tuple(label["r_Vo2To_vbs_true"]))
    config = _config(toy_run, shirt, tmp_path, starts=starts)
    loaded = load_model(toy_run[0], device="cpu")
    sequence = read_sequence(config.sequence, 0, 1)
    poses = Inversion.create(config)._starts(loaded, sequence, torch.zeros(3), [None], None)
    truth = torch.as_tensor(loaded.dataset_to_model(sequence.frames[0].c2w_true), dtype=torch.float32)
    torch.testing.assert_close(poses[0], truth, atol=1e-5, rtol=1e-5)  # the first start is the prior itself
    angles = geodesic_deg(poses[:, :3, :3], truth[None, :3, :3].expand(6, 3, 3))
    assert float(angles[1:].min()) > 0.1 and float(angles.max()) <= 10.0 * np.sqrt(3) + 1e-3
    with pytest.raises(InversionError, match="prior-q"):
        Inversion.create(replace(config, starts=StartConfig(source="prior")))._starts(loaded, sequence,
                                                                                     torch.zeros(3), [None], None)
