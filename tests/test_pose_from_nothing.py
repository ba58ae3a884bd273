"""``ns-invert`` with no option that needs the truth: it tracks from the view bank, never reads the labels,
goes on through a frame without the object, and refuses a mask folder that does not fit."""

import dataclasses
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from nerfinv_plugin.cli.invert import entrypoint
from nerfinv_plugin.initialization.bank import BankConfig
from nerfinv_plugin.inversion import reanchor as reanchor_module
from nerfinv_plugin.inversion import session as session_module
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.session import Events, Inversion
from nerfinv_plugin.inversion.settings import InvertConfig
from nerfinv_plugin.results.folder import RunFolder
from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.trajectories import TrajectorySpec


@pytest.fixture(scope="module")
def shirt(toy_run, tmp_path_factory) -> Path:
    """A SHIRT root with a 6-frame roe1 trajectory of the toy scene."""
    out = tmp_path_factory.mktemp("nothing")
    write_shirt_trajectories(out, "toy", [TrajectorySpec(kind="roe1", num_frames=6, range_m=5.0)],
                             speedplus_like_camera(80, 50), False, seed=4, spp=32, step=lambda: None)
    return out / "shirt"


@pytest.fixture(scope="module", autouse=True)
def bank_cache(tmp_path_factory):
    """One bank cache for the module: the first run renders, the others read it."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("NERFINV_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


def _folder_of(shirt: Path, out: Path, poses: str) -> Path:
    """The roe1 images as an image folder with camera.json, and poses.json: 'true', 'random' or 'none'."""
    out.mkdir(parents=True)
    for image in sorted((shirt / "roe1" / "synthetic" / "images").iterdir()):
        shutil.copy(image, out / image.name)
    shutil.copy(shirt / "camera.json", out / "camera.json")
    labels = json.loads((shirt / "roe1" / "roe1.json").read_text())
    if poses == "random":
        rng = np.random.default_rng(7)
        for label in labels:
            q = rng.normal(size=4)
            label["q_vbs2tango_true"] = (q / np.linalg.norm(q)).tolist()
            label["r_Vo2To_vbs_true"] = rng.uniform(-3, 3, size=3).tolist()
    if poses != "none":
        (out / "poses.json").write_text(json.dumps(labels))
    return out


def test_the_bare_command_tracks_the_fixture_from_nothing(toy_run, shirt, tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["ns-invert", "--load-config", str(toy_run[0]), "--sequence",
                                      str(shirt / "roe1"), "--output-dir", str(tmp_path), "--timestamp", "t"])
    entrypoint()
    run = tmp_path / "roe1" / "nerfinv" / "t"
    rows = RunFolder(run).rows()
    errors = np.array([r.rotation_deg for r in rows])
    assert len(rows) == 6 and (errors[2:] < 10.0).all(), errors
    summary = json.loads((run / "summary.json").read_text())
    assert summary["starts"] == "bank" and summary["bank"]["views"] == 642
    assert 0.72 < summary["target_radius_m"] < 1.1  # read off the model: the toy reaches 0.73 m from its centre


def test_twice_the_iterations_per_frame_end_no_worse(toy_run, shirt, tmp_path):
    """Issue 13's check against drift along the weak direction, for the default optimizer: twice Adam's
    iterations per frame, on the bare command's random pixels about the object, early stopping and pruning
    off (as by default), end no more than 0.5 degrees worse in the median over three seeds (four frames).
    Gauss-Newton passed the same check (with twice its trial steps, on interest regions) on one training of
    this fixture and failed it on another, with this session's code and the day before's alike
    (docs/method.md): it is not held to it."""
    finals = {}
    for label, optimizer in (("once", OptimizerConfig(iterations=60)), ("twice", OptimizerConfig(iterations=120))):
        for seed in (0, 1, 2):
            config = _quick(toy_run, shirt / "roe1", tmp_path / f"{label}-{seed}", stop=4, seed=seed,
                            optimizer=optimizer, sampling="random")
            assert config.sample_region == "object" == InvertConfig().sample_region
            assert optimizer.patience is None and optimizer.prune_every is None
            rows = RunFolder(Path(Inversion.create(config).run().run)).rows()
            errors = np.array([r.rotation_deg for r in rows])
            assert (errors[1:] < 10.0).all(), (label, seed, errors)
            finals[label, seed] = errors[-1]
    default = np.median([finals["once", s] for s in (0, 1, 2)])
    doubled = np.median([finals["twice", s] for s in (0, 1, 2)])
    assert doubled <= default + 0.5, " ".join(f"{k}={v:.2f}" for k, v in finals.items())


def _quick(toy_run, sequence: Path, out: Path, **changes) -> InvertConfig:
    return InvertConfig(load_config=toy_run[0], sequence=str(sequence), output_dir=out, name="e", timestamp="t",
                        device="cpu", pixels=128, eval_pixels=512, bank=BankConfig(subdivisions=2),
                        **({"optimizer": OptimizerConfig(iterations=15)} | changes))


@pytest.mark.parametrize("enabled", [True, False])
def test_reanchor_moves_the_carried_candidates_before_each_later_frame(toy_run, shirt, tmp_path, monkeypatch,
                                                                        enabled):
    """With ``--reanchor`` the candidates a step carried are moved before each frame after the first, by the
    anchor measured on the best of them: in range by its factor (1 on this steady roe1, where changes under
    2% are left out), in image position by its shift, attitudes kept; without it nothing moves."""
    seen = []

    def recording(c2w, best, centre, anchor, intrinsics):
        moved = reanchor_module.reanchor(c2w, best, centre, anchor, intrinsics)
        before_px, before = reanchor_module.project_centre(c2w[:1].double(), centre.double(), intrinsics)
        after_px, after = reanchor_module.project_centre(moved[:1].double(), centre.double(), intrinsics)
        assert torch.equal(moved[:, :3, :3], c2w[:, :3, :3])
        seen.append((anchor.range_scale, float(after[0] / before[0]), float((after_px - before_px).norm()),
                     c2w.shape[0]))
        return moved

    monkeypatch.setattr(session_module, "reanchor", recording)
    Inversion.create(_quick(toy_run, shirt / "roe1", tmp_path, stop=3, reanchor=enabled)).run()
    if not enabled:
        assert seen == []
        return
    assert len(seen) == 2, seen  # frames 1 and 2
    for scale, ratio, shift_px, carried in seen:
        assert abs(ratio - scale) < 1e-4 and shift_px > 0.1 and carried == 9, seen  # keep 3 x (1 + 2 spawned)


def test_the_default_path_never_reads_the_truth(toy_run, shirt, tmp_path):
    estimates = {}
    for poses in ("true", "none", "random"):
        folder = _folder_of(shirt, tmp_path / poses, poses)
        summary = Inversion.create(_quick(toy_run, folder, tmp_path / f"out-{poses}", stop=3)).run()
        estimates[poses] = [row.c2w_model for row in RunFolder(Path(summary.run)).rows()]
    assert estimates["true"] == estimates["none"] == estimates["random"]


def test_a_frame_without_the_object_keeps_the_prediction_and_the_run_goes_on(toy_run, shirt, tmp_path):
    folder = _folder_of(shirt, tmp_path / "frames", "true")
    second = sorted(p for p in folder.iterdir() if p.suffix in (".png", ".jpg"))[1]
    cv2.imwrite(str(second), np.zeros_like(cv2.imread(str(second))))
    warnings: list[str] = []
    summary = Inversion.create(_quick(toy_run, folder, tmp_path / "out", stop=3),
                               Events(warn=warnings.append)).run()
    rows = RunFolder(Path(summary.run)).rows()
    assert [r.object_found for r in rows] == [True, False, True]
    assert rows[1].c2w_model == rows[0].c2w_model
    assert summary.frames_without_object == 1 and summary.complete
    assert any("no object found" in w and second.name in w for w in warnings)


def test_a_mask_folder_that_does_not_match_the_frames_is_one_line_and_exit_code_2(toy_run, shirt, tmp_path,
                                                                                    monkeypatch, capsys):
    masks = tmp_path / "masks"
    masks.mkdir()
    cv2.imwrite(str(masks / "unrelated.png"), np.zeros((50, 80), np.uint8))
    monkeypatch.setattr(sys, "argv", ["ns-invert", "--load-config", str(toy_run[0]), "--sequence",
                                      str(shirt / "roe1"), "--output-dir", str(tmp_path / "out"), "--masks",
                                      str(masks)])
    with pytest.raises(SystemExit) as exit_info:
        entrypoint()
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1 and "--masks" in err, err
    assert not (tmp_path / "out").exists()


def _flipped_start(truth_model: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The first frame's true pose turned half a turn about the model's z axis through the object centre."""
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    to_centre, from_centre = np.eye(4), np.eye(4)
    to_centre[:3, 3], from_centre[:3, 3] = centre, -centre
    return to_centre @ turn @ from_centre @ truth_model


@pytest.mark.parametrize("watch_count", [2, 0])
def test_the_bank_watch_takes_a_tracker_off_a_wrong_mode(toy_run, shirt, tmp_path, monkeypatch, watch_count):
    """Started half a turn from the truth, with the lost-object check off: the bank's watch brings the tracker
    to the truth within the six frames; without it the tracker stays far off."""
    def wrong_start(self, loaded, sequence, centre, detections, initializer):
        truth = loaded.dataset_to_model(sequence.frames[0].c2w_true)
        return torch.as_tensor(_flipped_start(truth, centre.numpy())[None], dtype=torch.float32)

    monkeypatch.setattr(Inversion, "_starts", wrong_start)
    config = _quick(toy_run, shirt / "roe1", tmp_path, lost_iou=0.0, watch_count=watch_count,
                    optimizer=OptimizerConfig(iterations=30))
    summary = Inversion.create(config).run()
    rows = RunFolder(Path(summary.run)).rows()
    errors = np.array([r.rotation_deg for r in rows])
    assert errors[0] > 90.0, errors  # the start really was the wrong mode
    added = [r.bank_added for r in rows]
    if watch_count:
        assert errors[-2:].max() < 10.0 and sum(added) > 0, (errors, added)
    else:
        assert errors[-2:].min() > 30.0 and sum(added) == 0, (errors, added)


def test_the_bank_watch_skips_frames_that_cut_the_object(toy_run, shirt, tmp_path, monkeypatch):
    """The same wrong start and watch as above, with every frame's object marked as touching the border: the
    bank's hypotheses of a cut silhouette are not trusted, so none joins and the tracker stays off."""
    def wrong_start(self, loaded, sequence, centre, detections, initializer):
        truth = loaded.dataset_to_model(sequence.frames[0].c2w_true)
        return torch.as_tensor(_flipped_start(truth, centre.numpy())[None], dtype=torch.float32)

    found = Inversion._detections

    def cut(self, sequence):
        detections, seconds = found(self, sequence)
        return [dataclasses.replace(d, touches_border=True) for d in detections], seconds

    monkeypatch.setattr(Inversion, "_starts", wrong_start)
    monkeypatch.setattr(Inversion, "_detections", cut)
    config = _quick(toy_run, shirt / "roe1", tmp_path, lost_iou=0.0, watch_count=2,
                    optimizer=OptimizerConfig(iterations=30))
    rows = RunFolder(Path(Inversion.create(config).run().run)).rows()
    errors = np.array([r.rotation_deg for r in rows])
    assert errors[-2:].min() > 30.0 and sum(r.bank_added for r in rows) == 0, errors
