"""``ns-invert-psnr`` and ``model.evaluate``: the three readers (Blender, nerfstudio, SPEED+) give the same
views as their dataparsers, score the same views the same, and the all-black baseline is what it says."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.data.utils.dataparsers_utils import get_train_eval_split_fraction
from PIL import Image

from nerfinv_plugin.cli import psnr as psnr_cli
from nerfinv_plugin.data.speedplus import SpeedPlusDataParserConfig
from nerfinv_plugin.model.evaluate import (
    DataFormatError,
    detect_format,
    model_poses,
    nerfstudio_views,
    psnr,
    read_held_out,
    score_split,
    score_views,
    speedplus_views,
)
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.synth.speedplus import write_speedplus


@pytest.fixture(scope="module")
def loaded(toy_run) -> LoadedModel:
    return load_model(toy_run[0], device="cpu")


@pytest.fixture(scope="module")
def blender_score(loaded, toy_run):
    return score_split(loaded, toy_run[1], "blender", "test")


def frame_only(transform: np.ndarray, scale: float) -> LoadedModel:
    """A LoadedModel holding nothing but a dataparser transform: enough for :func:`model_poses`."""
    t4 = np.eye(4)
    t4[:3] = np.asarray(transform, dtype=np.float64)[:3]
    return LoadedModel(None, None, Path(), 0, torch.device("cpu"), t4, float(scale))


def _noop() -> None:
    pass


def test_blender_and_nerfstudio_readers_score_the_same_views_the_same(loaded, blender_score, toy_run, tmp_path):
    data = toy_run[1]
    # The folder's own transforms.json lists the test views in test_filenames.
    via_file = score_split(loaded, data, "nerfstudio", "test")
    # A transforms.json elsewhere restricted to the test frames (absolute paths), with only test_filenames.
    meta = json.loads((data / "transforms.json").read_text())
    test = set(meta["test_filenames"])
    frames = [{**f, "file_path": str(data / f["file_path"])} for f in meta["frames"] if f["file_path"] in test]
    restricted = {k: v for k, v in meta.items() if not k.endswith("_filenames")}
    restricted.update(frames=frames, test_filenames=[f["file_path"] for f in frames])
    (tmp_path / "transforms.json").write_text(json.dumps(restricted))
    via_copy = score_views(loaded, nerfstudio_views(tmp_path, "test"))

    blender = {v.file.resolve(): v.psnr for v in blender_score.views}
    assert len(blender) == 6
    for scores in (via_file.views, via_copy):
        other = {v.file.resolve(): v.psnr for v in scores}
        assert other.keys() == blender.keys()
        for path, value in blender.items():
            assert other[path] == pytest.approx(value, abs=1e-4), path
    assert via_file.mean_psnr == pytest.approx(blender_score.mean_psnr, abs=1e-4)
    assert via_file.black_psnr == pytest.approx(blender_score.black_psnr, abs=1e-9)


def test_black_psnr_equals_an_independent_computation(blender_score, toy_run):
    data = toy_run[1]
    meta = json.loads((data / "transforms_test.json").read_text())
    values = []
    for frame in meta["frames"]:
        rgba = np.asarray(Image.open(data / f"{frame['file_path'][2:]}.png"), dtype=np.float64) / 255.0
        over_black = rgba[..., :3] * rgba[..., 3:]
        values.append(-10.0 * np.log10(np.mean(over_black**2)))
    # The reader holds images in float32: agreement to float32 rounding, far below the 0.01 dB printed.
    assert blender_score.black_psnr == pytest.approx(float(np.mean(values)), abs=1e-5)
    assert [v.black_psnr for v in blender_score.views] == pytest.approx(values, abs=1e-5)
    assert blender_score.mean_psnr == pytest.approx(float(np.mean([v.psnr for v in blender_score.views])))
    assert blender_score.margin_db == pytest.approx(blender_score.mean_psnr - blender_score.black_psnr)
    assert blender_score.margin_db > 3.0  # the trained toy model renders the object, not only black


def test_psnr_counts_only_valid_pixels():
    a, b = np.zeros((4, 5, 3)), np.zeros((4, 5, 3))
    b[0] = 0.5  # wrong only in the first row
    valid = np.ones((4, 5), dtype=bool)
    valid[0] = False
    assert psnr(a, b, valid) == float("inf")
    assert psnr(a, b) == pytest.approx(-10 * np.log10(0.25 / 4))


def test_format_detection(toy_run, tmp_path):
    assert detect_format(toy_run[1]) == "blender"  # it holds both Blender files and a transforms.json
    layouts = {"blender": ["transforms_test.json"], "nerfstudio": ["transforms.json"],
               "speedplus": ["synthetic/validation.json"], "speedplus-camera": ["camera.json", "synthetic/"]}
    for name, files in layouts.items():
        folder = tmp_path / name
        for file in files:
            if file.endswith("/"):
                (folder / file).mkdir(parents=True)
            else:
                (folder / file).parent.mkdir(parents=True, exist_ok=True)
                (folder / file).write_text("{}")
        assert detect_format(folder) == name.split("-")[0]
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match="cannot tell the format"):
        detect_format(tmp_path / "empty")
    with pytest.raises(DataFormatError, match="cannot tell the format"):
        read_held_out(tmp_path / "empty")


def test_cli_prints_scores_and_fails_in_one_line_on_unknown_data(toy_run, tmp_path, monkeypatch, capsys):
    config, data = toy_run
    monkeypatch.setattr(sys, "argv", ["ns-invert-psnr", "--load-config", str(config), "--data", str(data),
                                      "--format", "nerfstudio", "--device", "cpu"])
    psnr_cli.entrypoint()
    out = capsys.readouterr().out
    assert "test/r_000.png:" in out and "all-black" in out and "margin +" in out
    assert "transforms.json test_filenames" in out

    (tmp_path / "empty").mkdir()
    monkeypatch.setattr(sys, "argv", ["ns-invert-psnr", "--load-config", str(config), "--data",
                                      str(tmp_path / "empty"), "--device", "cpu"])
    with pytest.raises(SystemExit) as exit_info:
        psnr_cli.entrypoint()
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "cannot tell the format" in err and "Traceback" not in err
    assert len(err.splitlines()) == 1


def _nerfstudio_tree(toy_data: Path, folder: Path, count: int, rng: np.random.Generator,
                     applied_transform: list | None = None) -> None:
    """``count`` frames (links to the toy images) in shuffled order, per-frame intrinsics, no split lists."""
    meta = json.loads((toy_data / "transforms.json").read_text())
    frames = []
    for k, index in enumerate(rng.permutation(count)):
        source = toy_data / meta["frames"][index]["file_path"]
        (folder / "images").mkdir(parents=True, exist_ok=True)
        (folder / "images" / f"frame_{index:05d}.png").symlink_to(source)
        frames.append({"file_path": f"images/frame_{index:05d}.png",
                       "transform_matrix": meta["frames"][index]["transform_matrix"],
                       "fl_x": meta["fl_x"] * (1 + 0.01 * k), "fl_y": meta["fl_y"] * (1 + 0.01 * k),
                       "cx": meta["cx"] + 0.1 * k, "cy": meta["cy"] - 0.1 * k, "w": meta["w"], "h": meta["h"]})
    out = {"camera_model": "OPENCV", "frames": frames}
    if applied_transform is not None:
        out["applied_transform"] = applied_transform
    (folder / "transforms.json").write_text(json.dumps(out))


def test_nerfstudio_default_split_and_frame_match_nerfstudio(toy_run, tmp_path):
    rng = np.random.default_rng(3)
    applied = [[0.0, 1.0, 0.0, 0.2], [1.0, 0.0, 0.0, -0.1], [0.0, 0.0, -1.0, 0.3]]
    _nerfstudio_tree(toy_run[1], tmp_path, 23, rng, applied)
    names = sorted(tmp_path / "images" / p.name for p in (tmp_path / "images").iterdir())
    i_train, i_eval = get_train_eval_split_fraction(names, 0.9)
    assert len(i_eval) == 2  # 23 - ceil(20.7)
    parser = NerfstudioDataParserConfig(data=tmp_path)
    for split, indices in (("test", i_eval), ("val", i_eval), ("train", i_train)):
        held_out = nerfstudio_views(tmp_path, split, parser)
        assert [v.image for v in held_out.views] == [names[i] for i in indices]
        # nerfstudio's own dataparser: the same images, and its poses are ours through the saved transform.
        outputs = parser.setup().get_dataparser_outputs(split)
        assert [Path(p) for p in outputs.image_filenames] == [v.image for v in held_out.views]
        frame = frame_only(outputs.dataparser_transform.numpy(), outputs.dataparser_scale)
        np.testing.assert_allclose(model_poses(frame, held_out)[:, :3],
                                   outputs.cameras.camera_to_worlds.numpy(), atol=1e-5)
        np.testing.assert_allclose([v.intrinsics.fx for v in held_out.views], outputs.cameras.fx[:, 0], rtol=1e-6)
        np.testing.assert_allclose([v.intrinsics.cy for v in held_out.views], outputs.cameras.cy[:, 0], rtol=1e-6)
    assert "train-split-fraction 0.9" in nerfstudio_views(tmp_path, "test").source


def test_nerfstudio_rejects_what_it_cannot_score(toy_run, tmp_path):
    _nerfstudio_tree(toy_run[1], tmp_path, 12, np.random.default_rng(0))
    meta = json.loads((tmp_path / "transforms.json").read_text())
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "k4": 0.1}))
    with pytest.raises(DataFormatError, match="k4"):
        nerfstudio_views(tmp_path, "test")
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "camera_model": "OPENCV_FISHEYE"}))
    with pytest.raises(DataFormatError, match="not a pinhole"):
        nerfstudio_views(tmp_path, "test")
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "train_filenames": []}))
    with pytest.raises(DataFormatError, match="no test views"):
        nerfstudio_views(tmp_path, "test")


@pytest.fixture(scope="module")
def speedplus_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("speedplus")
    write_speedplus(root, "tango", 4, 3, 40, 25, distortion=True, seed=2, spp=4, step=_noop)
    return root


def test_speedplus_views_are_the_dataparsers_held_out_views(speedplus_root):
    assert detect_format(speedplus_root) == "speedplus"
    for options in ({"scale_factor": 0.5}, {"eval_count": 2}):
        config = SpeedPlusDataParserConfig(data=speedplus_root, **options)
        held_out = speedplus_views(speedplus_root, "test", config)
        outputs = config.setup().get_dataparser_outputs("test")
        assert held_out.source == "synthetic/validation.json"
        assert [v.image for v in held_out.views] == list(outputs.image_filenames)
        frame = frame_only(outputs.dataparser_transform.numpy(), outputs.dataparser_scale)
        np.testing.assert_allclose(model_poses(frame, held_out)[:, :3],
                                   outputs.cameras.camera_to_worlds.numpy(), atol=1e-6)
        cameras = outputs.cameras
        view = held_out.views[0]
        assert (view.intrinsics.fx, view.intrinsics.cx, view.intrinsics.cy) == pytest.approx(
            (float(cameras.fx[0]), float(cameras.cx[0]), float(cameras.cy[0])))
        k1, k2, p1, p2, k3 = view.dist_coeffs
        np.testing.assert_allclose([k1, k2, k3, p1, p2], cameras.distortion_params[0, [0, 1, 2, 4, 5]], rtol=1e-6)


def test_speedplus_scoring_undistorts_and_masks(loaded, speedplus_root):
    score = score_split(loaded, speedplus_root, "auto", "val", max_views=2)
    assert score.format == "speedplus" and len(score.views) == 2 and "2 of 3 views" in score.source
    for view in score.views:
        assert view.valid is not None and view.valid.shape == view.observed.shape[:2]
        assert np.isfinite(view.psnr) and np.isfinite(view.black_psnr)
