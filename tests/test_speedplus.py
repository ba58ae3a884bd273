"""SPEED+: the writer's files, the ``speedplus-data`` dataparser (poses, intrinsics, distortion, subsets,
the HIL split, its error messages) and a short nerfacto-tiny training run on it."""

import copy
import json
import shutil
from importlib.metadata import entry_points
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nerfinv_plugin.data.speedplus import SpeedPlusDataParserConfig, speedplus_dataparser
from nerfinv_plugin.synth.speedplus import write_speedplus

TRAIN, VALIDATION = 6, 3
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def _noop() -> None:
    pass


@pytest.fixture(scope="module")
def speedplus(tmp_path_factory):
    root = tmp_path_factory.mktemp("speedplus")
    rendered = write_speedplus(root, "tango", TRAIN, VALIDATION, 40, 25, distortion=True, seed=1, spp=4,
                               step=_noop)
    return root, rendered


@pytest.fixture
def copy_of(speedplus, tmp_path):
    """A private copy of the written tree, for tests that break it."""
    root = tmp_path / "speedplus"
    shutil.copytree(speedplus[0], root)
    return root


def _outputs(root: Path, split: str = "train", **options):
    return SpeedPlusDataParserConfig(data=root, **options).setup().get_dataparser_outputs(split)


def _names(outputs) -> list[str]:
    return [path.name for path in outputs.image_filenames]


def _label_c2w_scipy(label: dict) -> np.ndarray:
    """Independent reading of a label: scipy wants scalar-last quaternions."""
    w, x, y, z = label["q_vbs2tango_true"]
    rot = Rotation.from_quat([x, y, z, w]).as_matrix()
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot.T, -rot.T @ np.asarray(label["r_Vo2To_vbs_true"])
    return c2w


def test_layout_and_keys(speedplus):
    root, rendered = speedplus
    camera = json.loads((root / "camera.json").read_text())
    assert set(camera) == {"Nu", "Nv", "ppx", "ppy", "fx", "fy", "ccx", "ccy", "cameraMatrix", "distCoeffs"}
    assert (camera["Nu"], camera["Nv"]) == (40, 25)
    assert camera["distCoeffs"] == pytest.approx(rendered.dist_coeffs.tolist())
    names = {"train": [f"img{k:06d}.jpg" for k in range(1, 7)], "validation": ["img000007.jpg", "img000008.jpg",
                                                                                 "img000009.jpg"]}
    for split, expected in names.items():
        labels = json.loads((root / "synthetic" / f"{split}.json").read_text())
        assert [label["filename"] for label in labels] == expected == rendered.filenames[split]
        assert all(set(label) == {"filename", "q_vbs2tango_true", "r_Vo2To_vbs_true"} for label in labels)
        for name in expected:
            image = cv2.imread(str(root / "synthetic" / "images" / name), cv2.IMREAD_UNCHANGED)
            assert image.shape == (25, 40, 3) and image.max() > 50  # RGB, the object in view


def test_labels_and_dataparser_poses_match_rendering(speedplus):
    root, rendered = speedplus
    scale = 0.5
    for split, ns_split in (("train", "train"), ("validation", "val"), ("validation", "test")):
        labels = json.loads((root / "synthetic" / f"{split}.json").read_text())
        from_labels = np.stack([_label_c2w_scipy(label) for label in labels])
        np.testing.assert_allclose(from_labels, rendered.c2w_opencv[split], atol=1e-9)
        expected = rendered.c2w_opencv[split] @ OPENCV_TO_OPENGL
        expected[:, :3, 3] *= scale
        outputs = _outputs(root, ns_split, scale_factor=scale)
        assert _names(outputs) == rendered.filenames[split]
        np.testing.assert_allclose(outputs.cameras.camera_to_worlds.numpy(), expected[:, :3], atol=1e-5)
        assert torch.equal(outputs.dataparser_transform, torch.eye(4)[:3])
        assert outputs.dataparser_scale == scale
        np.testing.assert_allclose(outputs.scene_box.aabb.numpy(), [[-0.5] * 3, [0.5] * 3])


def test_intrinsics_and_distortion_carried(speedplus):
    root, rendered = speedplus
    matrix = np.asarray(json.loads((root / "camera.json").read_text())["cameraMatrix"])
    cameras = _outputs(root).cameras
    np.testing.assert_allclose(cameras.fx.numpy(), matrix[0, 0], rtol=1e-6)
    np.testing.assert_allclose(cameras.fy.numpy(), matrix[1, 1], rtol=1e-6)
    np.testing.assert_allclose(cameras.cx.numpy(), matrix[0, 2] + 0.5, rtol=1e-6)  # nerfstudio: pixel centres
    np.testing.assert_allclose(cameras.cy.numpy(), matrix[1, 2] + 0.5, rtol=1e-6)  # at half-integers
    assert cameras.width.unique().tolist() == [40] and cameras.height.unique().tolist() == [25]
    k1, k2, p1, p2, k3 = rendered.dist_coeffs
    np.testing.assert_allclose(cameras.distortion_params.numpy(),
                               np.tile([k1, k2, k3, 0.0, p1, p2], (TRAIN, 1)), rtol=1e-6)


def test_rays_leave_distorted_pixels_where_opencv_says(speedplus):
    """A ray through a pixel of the distorted image must follow OpenCV's undistorted direction of that
    pixel: checks the coefficient order, the half-pixel offset and the camera axes together."""
    root, rendered = speedplus
    camera = rendered.camera
    cameras = _outputs(root).cameras
    pixels = np.array([[0.0, 0.0], [39.0, 24.0], [3.0, 20.0], [20.0, 12.0]])  # corners distort most
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    ideal = cv2.undistortPointsIter(pixels[:, None], camera.matrix, rendered.dist_coeffs, None, None, criteria)[:, 0]
    c2w = rendered.c2w_opencv["train"][2]
    expected = np.concatenate([ideal, np.ones((len(ideal), 1))], 1) @ c2w[:3, :3].T
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    coords = torch.tensor(pixels[:, ::-1] + 0.5, dtype=torch.float32)  # nerfstudio: (row, col), centres +0.5
    rays = cameras.generate_rays(camera_indices=torch.full((len(pixels), 1), 2), coords=coords)
    np.testing.assert_allclose(rays.origins.numpy(), np.tile(c2w[:3, 3], (len(pixels), 1)), atol=1e-5)
    np.testing.assert_allclose(rays.directions.numpy(), expected, atol=2e-6)
    shift_px = np.linalg.norm(ideal * camera.focal + camera.matrix[:2, 2] - pixels, axis=1)
    assert shift_px.max() > 0.5  # distortion moves the corners by half a pixel or more: it mattered


def test_grey_images_as_speedplus_ships_them(copy_of):
    """SPEED+ JPEGs are single-channel; nerfstudio must still get [H, W, 3] images."""
    from nerfstudio.data.datasets.base_dataset import InputDataset

    for path in (copy_of / "synthetic" / "images").glob("*.jpg"):
        cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    dataset = InputDataset(_outputs(copy_of))
    image = dataset.get_image_float32(0)
    assert image.shape == (25, 40, 3) and image.max() > 0.2
    assert torch.equal(image[..., 0], image[..., 2])


def test_subset_by_list_and_count(speedplus, tmp_path):
    root, _ = speedplus
    listing = tmp_path / "no-earth.txt"
    listing.write_text("# picked by hand\nimg000005.jpg\n\nimg000002.jpg\n  img000003.jpg  \nimg000006.jpg\n")
    assert _names(_outputs(root, subset_list=listing)) == ["img000002.jpg", "img000003.jpg", "img000005.jpg",
                                                           "img000006.jpg"]
    assert _names(_outputs(root, subset_count=3)) == ["img000002.jpg", "img000004.jpg", "img000006.jpg"]
    assert _names(_outputs(root, subset_count=2, subset_list=listing)) == ["img000003.jpg", "img000006.jpg"]
    assert _names(_outputs(root, subset_count=TRAIN)) == [f"img{k:06d}.jpg" for k in range(1, 7)]
    # The subset options choose training images; eval-count thins the val/test split.
    assert len(_outputs(root, "val", subset_count=1).image_filenames) == VALIDATION
    assert _names(_outputs(root, "val", eval_count=1)) == ["img000008.jpg"]


def test_hil_domain_split(speedplus, tmp_path):
    """lightbox/sunlamp labels exist only as test.json: labels 0, N, 2N, ... are held out."""
    src, _ = speedplus
    root = tmp_path / "speedplus"
    root.mkdir()
    shutil.copy(src / "camera.json", root / "camera.json")
    shutil.copytree(src / "synthetic" / "images", root / "sunlamp" / "images")
    labels = [json.loads((src / "synthetic" / f"{s}.json").read_text()) for s in ("train", "validation")]
    (root / "sunlamp" / "test.json").write_text(json.dumps(labels[0] + labels[1]))
    train = _names(_outputs(root, domain="sunlamp", hil_eval_interval=4))
    held_out = _names(_outputs(root, "val", domain="sunlamp", hil_eval_interval=4))
    assert held_out == ["img000001.jpg", "img000005.jpg", "img000009.jpg"]
    assert train == ["img000002.jpg", "img000003.jpg", "img000004.jpg", "img000006.jpg", "img000007.jpg",
                     "img000008.jpg"]
    assert _names(_outputs(root, "test", domain="sunlamp", hil_eval_interval=4)) == held_out
    listing = tmp_path / "list.txt"
    listing.write_text("img000005.jpg\n")
    with pytest.raises(ValueError, match="'img000005.jpg' .* not among the training labels of sunlamp/test.json"):
        _outputs(root, domain="sunlamp", hil_eval_interval=4, subset_list=listing)
    with pytest.raises(FileNotFoundError, match="lightbox/test.json"):
        _outputs(root, domain="lightbox")


def _break_camera_json(root: Path) -> None:
    camera = json.loads((root / "camera.json").read_text())
    camera["Nu"] = 48
    (root / "camera.json").write_text(json.dumps(camera))


def _v1_labels(root: Path) -> None:
    (root / "synthetic" / "train.json").write_text(
        '[{"filename": "img000001.jpg", "q_vbs2tango": [1, 0, 0, 0], "r_Vo2To_vbs_true": [0, 0, 5]}]')


def _unknown_in_list(root: Path) -> dict:
    listing = root / "list.txt"
    listing.write_text("img000002.jpg\nimg999999.jpg\nimg888888.jpg\n")
    return {"subset_list": listing}


BAD_INPUTS = {
    "no camera.json": (lambda root: (root / "camera.json").unlink(), "train", FileNotFoundError,
                       r"no camera.json in .*--data must be the SPEED\+ root"),
    "no label file": (lambda root: (root / "synthetic" / "validation.json").unlink(), "val", FileNotFoundError,
                      r"no label file .*synthetic/validation.json.*check --data and --domain"),
    "missing image": (lambda root: (root / "synthetic" / "images" / "img000004.jpg").unlink(), "train",
                      FileNotFoundError, r"img000004.jpg listed in synthetic/train.json does not exist"),
    "image size": (_break_camera_json, "train", ValueError,
                   r"img000001.jpg is 40x25 but camera.json says Nu x Nv = 48x25"),
    "unknown subset name": (_unknown_in_list, "train", ValueError,
                            r"'img999999.jpg' from subset list .* training labels .*2 of its 3 names are unknown"),
    "subset count too large": (lambda root: {"subset_count": 7}, "train", ValueError,
                               r"subset-count=7 but synthetic/train.json offers 6 labels"),
    "no subset list": (lambda root: {"subset_list": root / "nope.txt"}, "train", FileNotFoundError,
                       r"subset list .*nope.txt does not exist"),
    "v1 label keys": (_v1_labels, "train", ValueError,
                      r"label 0 in .*synthetic/train.json lacks 'q_vbs2tango_true'.*SPEED v1 label: rename"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_gives_one_line_message(copy_of, case):
    breaker, split, error, message = BAD_INPUTS[case]
    options = breaker(copy_of) or {}
    with pytest.raises(error, match=message) as caught:
        _outputs(copy_of, split, **options)
    assert "\n" not in str(caught.value)


def test_registered_as_nerfstudio_dataparser():
    (entry,) = [e for e in entry_points(group="nerfstudio.dataparser_configs") if e.name == "speedplus-data"]
    assert entry.load() is speedplus_dataparser
    assert isinstance(speedplus_dataparser.config, SpeedPlusDataParserConfig)


def test_nerfacto_tiny_trains_and_records_identity_transform(speedplus, tmp_path):
    from nerfinv_plugin.model.nerfacto_tiny import nerfacto_tiny

    root, _ = speedplus
    scale, iterations = 0.5, 30
    config = copy.deepcopy(nerfacto_tiny.config)
    config.pipeline.datamanager.dataparser = SpeedPlusDataParserConfig(data=root, scale_factor=scale)
    config.pipeline.datamanager.train_num_rays_per_batch = 128
    config.pipeline.model.background_color = "black"  # RGB images over black: nothing to learn opacity from
    config.pipeline.model.near_plane, config.pipeline.model.far_plane = 1.0 * scale, 12.0 * scale
    config.output_dir, config.experiment_name, config.timestamp = tmp_path, "speedplus", "run"
    config.max_num_iterations = config.steps_per_save = iterations
    config.logging.local_writer.enable = False
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    base = config.get_base_dir()
    assert (base / "nerfstudio_models" / f"step-{iterations - 1:09d}.ckpt").is_file()
    transforms = json.loads((base / "dataparser_transforms.json").read_text())
    assert transforms == {"transform": np.eye(4)[:3].tolist(), "scale": scale}
