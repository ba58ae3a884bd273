"""Reading observed sequences: SHIRT (both domains), Blender splits and image folders, with truth, image
processing (grey, alpha, undistortion, resizing), frame ranges, and one test per kind of bad input."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nerfinv_plugin.data.sequences import SequenceError, read_sequence
from nerfinv_plugin.synth.datasets import (
    SPEEDPLUS_DIST_COEFFS,
    TrainingSetSpec,
    speedplus_like_camera,
    write_shirt_trajectories,
    write_training_set,
)
from nerfinv_plugin.synth.trajectories import TrajectorySpec

WIDTH, HEIGHT = 32, 20
FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])
NAMES = [f"img{k:06d}.jpg" for k in range(1, 5)]


def _noop() -> None:
    pass


@pytest.fixture(scope="module")
def shirt(tmp_path_factory):
    """``(SHIRT root, rendered trajectory)``: 4 frames of roe1, no distortion; copy before editing."""
    out = tmp_path_factory.mktemp("shirt")
    [rendered] = write_shirt_trajectories(out, "toy", [TrajectorySpec(kind="roe1", num_frames=4, range_m=5.0)],
                                          speedplus_like_camera(WIDTH, HEIGHT), False, seed=0, spp=4, step=_noop)
    return out / "shirt", rendered


@pytest.fixture(scope="module")
def blender(tmp_path_factory) -> Path:
    """A Blender scene with train / val / test splits of RGBA PNGs; copy before editing."""
    out = tmp_path_factory.mktemp("blender")
    spec = TrainingSetSpec(train_views=1, val_views=1, test_views=3, width=WIDTH, height=HEIGHT)
    write_training_set(out, "toy", spec, seed=0, spp=4, step=_noop)
    return out


@pytest.fixture
def shirt_copy(shirt, tmp_path) -> Path:
    root = tmp_path / "shirt"
    shutil.copytree(shirt[0], root)
    return root


@pytest.fixture
def blender_copy(blender, tmp_path) -> Path:
    scene = tmp_path / "scene"
    shutil.copytree(blender, scene)
    return scene


def _folder_of(shirt_root: Path, folder: Path, camera: bool = True) -> Path:
    """The SHIRT images as a plain folder, with the SHIRT camera.json when asked."""
    shutil.copytree(shirt_root / "roe1" / "synthetic" / "images", folder)
    if camera:
        shutil.copy(shirt_root / "camera.json", folder / "camera.json")
    return folder


def _rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _camera_matrix(root: Path) -> np.ndarray:
    return np.asarray(json.loads((root / "camera.json").read_text())["cameraMatrix"])


def _expect(words: list[str], **kwargs) -> None:
    """``read_sequence(**kwargs)`` fails with one line that contains every word."""
    with pytest.raises(SequenceError) as info:
        read_sequence(**kwargs)
    message = str(info.value)
    assert "\n" not in message
    for word in words:
        assert word in message, f"{word!r} not in {message!r}"


# --- SHIRT -------------------------------------------------------------------------------------------


def test_shirt_truth_is_the_rendered_pose_in_opengl_axes(shirt):
    root, rendered = shirt
    seq = read_sequence(root / "roe1")
    assert (seq.kind, seq.source, seq.native_size, seq.has_truth) == ("shirt", root / "roe1" / "synthetic",
                                                                       (WIDTH, HEIGHT), True)
    assert [f.name for f in seq.frames] == NAMES
    for frame, c2w_cv, path in zip(seq.frames, rendered.c2w_opencv, rendered.image_paths):
        np.testing.assert_allclose(frame.c2w_true, c2w_cv @ FLIP_YZ, atol=1e-9)
        assert frame.image.dtype == np.uint8 and frame.image.shape == (HEIGHT, WIDTH, 3)
        np.testing.assert_array_equal(frame.image, _rgb(path))
    camera = speedplus_like_camera(WIDTH, HEIGHT)
    intr = seq.intrinsics
    # camera.json's matrix is OpenCV's (pixel centres at integers); nerfstudio's centres are half a pixel on.
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == pytest.approx((camera.focal, camera.focal, camera.cx + 0.5,
                                                                   camera.cy + 0.5))
    assert (intr.width, intr.height) == (WIDTH, HEIGHT)


def test_shirt_domain_spellings(shirt, shirt_copy):
    root, _ = shirt
    plain = read_sequence(str(root / "roe1"))
    synthetic = read_sequence(root / "roe1" / "synthetic")
    shutil.copytree(shirt_copy / "roe1" / "synthetic" / "images", shirt_copy / "roe1" / "lightbox" / "images")
    lightbox = read_sequence(shirt_copy / "roe1" / "lightbox")
    assert synthetic.source.name == "synthetic" and lightbox.source.name == "lightbox"
    for other in (synthetic, lightbox):
        assert other.intrinsics == plain.intrinsics
        for a, b in zip(plain.frames, other.frames, strict=True):
            assert a.name == b.name
            np.testing.assert_array_equal(a.image, b.image)
            np.testing.assert_array_equal(a.c2w_true, b.c2w_true)


def test_camera_argument_replaces_the_shirt_camera(shirt_copy, tmp_path):
    camera = json.loads((shirt_copy / "camera.json").read_text())
    camera["cameraMatrix"][0][0] *= 2
    explicit = tmp_path / "elsewhere.json"
    explicit.write_text(json.dumps(camera))
    assert read_sequence(shirt_copy / "roe1", camera=explicit).intrinsics.fx == pytest.approx(
        2 * _camera_matrix(shirt_copy)[0, 0])
    (shirt_copy / "camera.json").unlink()
    assert read_sequence(shirt_copy / "roe1", camera=explicit).has_truth


# --- Blender -----------------------------------------------------------------------------------------


def test_blender_split_poses_focal_and_alpha_over_black(blender):
    seq = read_sequence(f"{blender}:test")
    meta = json.loads((blender / "transforms_test.json").read_text())
    assert (seq.kind, seq.source, seq.native_size, seq.has_truth) == ("blender", blender / "transforms_test.json",
                                                                       (WIDTH, HEIGHT), True)
    assert [f.name for f in seq.frames] == ["r_000.png", "r_001.png", "r_002.png"]
    focal = 0.5 * WIDTH / np.tan(0.5 * meta["camera_angle_x"])
    intr = seq.intrinsics
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == pytest.approx((focal, focal, WIDTH / 2, HEIGHT / 2))
    for frame, entry in zip(seq.frames, meta["frames"], strict=True):
        np.testing.assert_array_equal(frame.c2w_true, np.asarray(entry["transform_matrix"]))
        rgba = cv2.imread(str(blender / f"{entry['file_path']}.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
        assert rgba.shape[2] == 4 and rgba[..., 3].min() < 255  # the test means something only with alpha
        over_black = rgba[..., 2::-1] * rgba[..., 3:] / 255.0
        assert np.abs(frame.image.astype(np.float64) - over_black).max() <= 0.5


def test_blender_file_paths_with_suffix_and_without_dot_prefix(blender_copy):
    meta = json.loads((blender_copy / "transforms_test.json").read_text())
    for entry in meta["frames"]:
        entry["file_path"] = entry["file_path"].removeprefix("./") + ".png"
    (blender_copy / "transforms_mine.json").write_text(json.dumps(meta))
    mine = read_sequence(f"{blender_copy}:mine")
    test = read_sequence(f"{blender_copy}:test")
    for a, b in zip(mine.frames, test.frames, strict=True):
        np.testing.assert_array_equal(a.image, b.image)


# --- folders -----------------------------------------------------------------------------------------


def test_folder_without_poses_has_no_truth(shirt, tmp_path):
    root, rendered = shirt
    folder = _folder_of(root, tmp_path / "frames")
    seq = read_sequence(folder)
    assert (seq.kind, seq.source, seq.has_truth) == ("folder", folder, False)
    assert [f.name for f in seq.frames] == NAMES
    assert all(f.c2w_true is None for f in seq.frames)
    np.testing.assert_array_equal(seq.frames[2].image, _rgb(rendered.image_paths[2]))


def test_folder_poses_json_gives_truth_to_the_frames_it_lists(shirt, tmp_path):
    root, rendered = shirt
    labels = json.loads((root / "roe1" / "roe1.json").read_text())
    folder = _folder_of(root, tmp_path / "frames")
    (folder / "poses.json").write_text(json.dumps([labels[3], labels[1]]))
    seq = read_sequence(folder)
    assert not seq.has_truth
    assert seq.frames[0].c2w_true is None and seq.frames[2].c2w_true is None
    for k in (1, 3):
        np.testing.assert_allclose(seq.frames[k].c2w_true, rendered.c2w_opencv[k] @ FLIP_YZ, atol=1e-9)
    (folder / "poses.json").write_text(json.dumps(labels))
    assert read_sequence(folder).has_truth


def test_grey_and_16_bit_images_become_three_equal_channels(tmp_path):
    folder = tmp_path / "grey"
    folder.mkdir()
    grey = np.random.default_rng(0).integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    cv2.imwrite(str(folder / "a.png"), grey)
    cv2.imwrite(str(folder / "b.png"), grey.astype(np.uint16) * 257)
    camera = {"Nu": WIDTH, "Nv": HEIGHT, "cameraMatrix": speedplus_like_camera(WIDTH, HEIGHT).matrix.tolist(),
              "distCoeffs": [0.0] * 5}
    (folder / "camera.json").write_text(json.dumps(camera))
    seq = read_sequence(folder)
    for frame in seq.frames:
        assert frame.image.shape == (HEIGHT, WIDTH, 3) and frame.image.dtype == np.uint8
        for channel in range(3):
            np.testing.assert_array_equal(frame.image[..., channel], grey)


# --- processing --------------------------------------------------------------------------------------


def _project_opengl(c2w_gl: np.ndarray, intr, point: np.ndarray) -> np.ndarray:
    """Pixel (continuous, nerfstudio convention) of a world point seen from an OpenGL camera."""
    w2c = np.linalg.inv(c2w_gl)
    x, y, z = w2c[:3, :3] @ point + w2c[:3, 3]
    return np.array([intr.cx + intr.fx * x / -z, intr.cy - intr.fy * y / -z])


@pytest.mark.parametrize("size", [(16, 10), (16, 20), (48, 30)])
def test_resolution_scales_intrinsics_and_projections(shirt, size):
    root, _ = shirt
    native = read_sequence(root / "roe1")
    seq = read_sequence(root / "roe1", resolution=size)
    sx, sy = size[0] / WIDTH, size[1] / HEIGHT
    a, b = native.intrinsics, seq.intrinsics
    assert (b.width, b.height) == size and seq.native_size == (WIDTH, HEIGHT)
    assert (b.fx, b.fy, b.cx, b.cy) == pytest.approx((a.fx * sx, a.fy * sy, a.cx * sx, a.cy * sy), rel=1e-12)
    labels = json.loads((root / "roe1" / "roe1.json").read_text())
    matrix = _camera_matrix(root)
    points = np.array([[0.0, 0.0, 0.0], [0.37, -0.385, 0.32], [-0.54, 0.49, 0.25]])
    for frame, label, native_frame in zip(seq.frames, labels, native.frames, strict=True):
        assert frame.image.shape == (size[1], size[0], 3)
        np.testing.assert_array_equal(frame.image, cv2.resize(native_frame.image, size, interpolation=cv2.INTER_AREA))
        w, x, y, z = label["q_vbs2tango_true"]
        rvec = Rotation.from_quat([x, y, z, w]).as_rotvec()
        pixels, _ = cv2.projectPoints(points, rvec, np.asarray(label["r_Vo2To_vbs_true"]), matrix, None)
        for point, opencv_pixel in zip(points, pixels[:, 0]):
            expected = (opencv_pixel + 0.5) * [sx, sy]  # OpenCV pixel centres are half a pixel before ours
            np.testing.assert_allclose(_project_opengl(frame.c2w_true, b, point), expected, atol=1e-7)


def test_undistortion_follows_camera_json(shirt_copy):
    camera = json.loads((shirt_copy / "camera.json").read_text())
    camera["distCoeffs"] = SPEEDPLUS_DIST_COEFFS.tolist()
    (shirt_copy / "camera.json").write_text(json.dumps(camera))
    matrix = np.asarray(camera["cameraMatrix"])
    seq = read_sequence(shirt_copy / "roe1")
    small = read_sequence(shirt_copy / "roe1", resolution=(16, 10))
    assert seq.intrinsics.fx == pytest.approx(matrix[0, 0]) and seq.intrinsics.cx == pytest.approx(matrix[0, 2] + 0.5)
    changed = 0
    for frame, small_frame in zip(seq.frames, small.frames, strict=True):
        raw = cv2.imread(str(shirt_copy / "roe1" / "synthetic" / "images" / frame.name), cv2.IMREAD_COLOR)
        expected = cv2.cvtColor(cv2.undistort(raw, matrix, SPEEDPLUS_DIST_COEFFS), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(frame.image, expected)
        np.testing.assert_array_equal(small_frame.image, cv2.resize(expected, (16, 10), interpolation=cv2.INTER_AREA))
        changed += int(np.any(expected != cv2.cvtColor(raw, cv2.COLOR_BGR2RGB)))
    assert changed == len(seq.frames)


def test_frame_range_is_applied_before_reading_images(shirt, shirt_copy):
    root, rendered = shirt
    assert [f.name for f in read_sequence(root / "roe1", start=1, stride=2).frames] == [NAMES[1], NAMES[3]]
    assert [f.name for f in read_sequence(root / "roe1", stop=3).frames] == NAMES[:3]
    assert [f.name for f in read_sequence(root / "roe1", start=2, stop=3).frames] == [NAMES[2]]
    picked = read_sequence(root / "roe1", start=3, stop=99).frames
    assert [f.name for f in picked] == [NAMES[3]]
    np.testing.assert_allclose(picked[0].c2w_true, rendered.c2w_opencv[3] @ FLIP_YZ, atol=1e-9)
    (shirt_copy / "roe1" / "synthetic" / "images" / NAMES[0]).unlink()
    assert len(read_sequence(shirt_copy / "roe1", start=1).frames) == 3


# --- bad input ---------------------------------------------------------------------------------------


def test_missing_path(tmp_path):
    _expect([str(tmp_path / "nope"), "does not exist", "roeN", "<scene>:<split>", "camera.json"],
            spec=tmp_path / "nope")


def test_path_matching_no_layout(shirt, blender, tmp_path):
    _expect([str(tmp_path), "matches no sequence layout", "roeN", "<scene>:<split>", "camera.json"], spec=tmp_path)
    _expect(["matches no sequence layout", f"{blender}:test"], spec=blender)
    _expect(["matches no sequence layout", str(shirt[0] / "roe1")], spec=shirt[0])


def test_missing_split(blender):
    _expect(["transforms_nosuch.json", "does not exist", "test, train, val"], spec=f"{blender}:nosuch")


def test_missing_camera_json(shirt, shirt_copy, tmp_path):
    (shirt_copy / "camera.json").unlink()
    _expect([f"no camera.json in {shirt_copy}", "--camera"], spec=shirt_copy / "roe1")
    folder = _folder_of(shirt[0], tmp_path / "frames", camera=False)
    _expect([f"no camera.json in {folder}", "--camera"], spec=folder)
    _expect([str(tmp_path / "cam.json"), "does not exist", "--camera"], spec=folder, camera=tmp_path / "cam.json")


def test_camera_argument_with_blender_split(blender, shirt):
    _expect(["--camera", "camera_angle_x"], spec=f"{blender}:test", camera=shirt[0] / "camera.json")


def test_unreadable_or_incomplete_label_files(shirt_copy):
    labels_path = shirt_copy / "roe1" / "roe1.json"
    labels = json.loads(labels_path.read_text())
    labels_path.write_text("[{not json")
    _expect(["cannot read", str(labels_path)], spec=shirt_copy / "roe1")
    del labels[2]["r_Vo2To_vbs_true"]
    labels_path.write_text(json.dumps(labels))
    _expect(["label 2", str(labels_path), "'r_Vo2To_vbs_true'"], spec=shirt_copy / "roe1")
    labels[2]["r_Vo2To_vbs_true"] = [1.0, 2.0]
    labels_path.write_text(json.dumps(labels))
    _expect(["label 2", "'r_Vo2To_vbs_true'", "3-vector"], spec=shirt_copy / "roe1")


def test_incomplete_camera_json(shirt_copy):
    camera = json.loads((shirt_copy / "camera.json").read_text())
    del camera["cameraMatrix"]
    (shirt_copy / "camera.json").write_text(json.dumps(camera))
    _expect([str(shirt_copy / "camera.json"), "'cameraMatrix'"], spec=shirt_copy / "roe1")


def test_incomplete_transforms_file(blender_copy):
    path = blender_copy / "transforms_test.json"
    meta = json.loads(path.read_text())
    del meta["frames"][1]["transform_matrix"]
    path.write_text(json.dumps(meta))
    _expect(["frame 1", str(path), "'transform_matrix'"], spec=f"{blender_copy}:test")
    del meta["camera_angle_x"]
    path.write_text(json.dumps(meta))
    _expect([str(path), "'camera_angle_x'"], spec=f"{blender_copy}:test")


def test_missing_image(shirt_copy, blender_copy):
    (shirt_copy / "roe1" / "synthetic" / "images" / NAMES[2]).unlink()
    _expect([NAMES[2], "does not exist", "roe1.json"], spec=shirt_copy / "roe1")
    (blender_copy / "test" / "r_001.png").unlink()
    _expect(["r_001.png", "does not exist", "transforms_test.json"], spec=f"{blender_copy}:test")


def test_unknown_image_in_poses_json_and_undecodable_image(shirt, tmp_path):
    labels = json.loads((shirt[0] / "roe1" / "roe1.json").read_text())
    folder = _folder_of(shirt[0], tmp_path / "frames")
    (folder / "poses.json").write_text(json.dumps([{**labels[0], "filename": "img999999.jpg"}]))
    _expect(["img999999.jpg", "not an image", "poses.json"], spec=folder)
    (folder / "poses.json").unlink()
    (folder / NAMES[1]).write_bytes(b"not a jpeg")
    _expect(["cannot decode", NAMES[1]], spec=folder)


def test_image_size_differs_from_camera_json(shirt, tmp_path):
    folder = _folder_of(shirt[0], tmp_path / "frames")
    for name in NAMES:
        cv2.imwrite(str(folder / name), np.zeros((25, 40, 3), np.uint8))
    _expect([NAMES[0], "40x25", f"{WIDTH}x{HEIGHT}", "camera.json"], spec=folder)


def test_images_of_different_sizes(blender_copy):
    cv2.imwrite(str(blender_copy / "test" / "r_002.png"), np.zeros((25, 40, 4), np.uint8))
    _expect(["r_002.png", "40x25", "r_000.png", f"{WIDTH}x{HEIGHT}", "one size"], spec=f"{blender_copy}:test")


def test_empty_sequence(shirt, shirt_copy):
    _expect(["select nothing", "4 frames", "start below 4"], spec=shirt[0] / "roe1", start=10)
    _expect(["select nothing", "4 frames"], spec=shirt[0] / "roe1", start=2, stop=2)
    (shirt_copy / "roe1" / "roe1.json").write_text("[]")
    _expect(["roe1.json", "lists no frames"], spec=shirt_copy / "roe1")


def test_unknown_shirt_domain(shirt):
    _expect([str(shirt[0] / "roe1" / "sunlamp"), "not a SHIRT domain", "synthetic", "lightbox"],
            spec=shirt[0] / "roe1" / "sunlamp")


@pytest.mark.parametrize("bad", [{"start": -1}, {"stride": 0}, {"stop": -2}])
def test_invalid_frame_range(shirt, bad):
    _expect(["invalid frame range", "stride >= 1"], spec=shirt[0] / "roe1", **bad)


@pytest.mark.parametrize("resolution", [(0, 10), (16.5, 10), (16,)])
def test_invalid_resolution(shirt, resolution):
    _expect(["invalid resolution", "(width, height)"], spec=shirt[0] / "roe1", resolution=resolution)
