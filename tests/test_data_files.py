"""The readers every data path shares: camera.json, pose labels and images (``nerfinv_plugin.data``)."""

import json

import cv2
import numpy as np
import pytest
from PIL import Image

from nerfinv_plugin.data import speedplus
from nerfinv_plugin.data.camera_and_labels import DataFileError, read_camera, read_label_poses, read_labels
from nerfinv_plugin.data.images import ImageError, read_rgb8, read_rgb_over_black
from nerfinv_plugin.geometry.frames import label_to_c2w_opencv, opencv_to_opengl

MATRIX = [[300.0, 0.0, 119.5], [0.0, 300.0, 74.5], [0.0, 0.0, 1.0]]


def _camera(path, **fields) -> None:
    path.write_text(json.dumps({"Nu": 240, "Nv": 150, "cameraMatrix": MATRIX} | fields))


def test_camera_json_is_read_once_for_sequences_and_speedplus(tmp_path):
    _camera(tmp_path / "camera.json", distCoeffs=[0.1, -0.2, 0.001, 0.002])
    camera = read_camera(tmp_path / "camera.json")
    assert (camera.width, camera.height) == (240, 150) and camera.matrix.tolist() == MATRIX
    assert camera.dist.tolist() == [0.1, -0.2, 0.001, 0.002]
    parsed = speedplus.read_camera(tmp_path)  # padded to OpenCV's five for nerfstudio
    assert parsed.matrix.tolist() == MATRIX and parsed.dist_coeffs.tolist() == [0.1, -0.2, 0.001, 0.002, 0.0]
    _camera(tmp_path / "camera.json")  # no distCoeffs: no distortion, for both
    assert read_camera(tmp_path / "camera.json").dist.size == 0
    assert not np.any(speedplus.read_camera(tmp_path).dist_coeffs)
    _camera(tmp_path / "camera.json", distCoeffs=[0.0] * 8)  # OpenCV takes 8; nerfstudio no more than 5
    assert read_camera(tmp_path / "camera.json").dist.size == 8
    with pytest.raises(ValueError, match="got 8 values; nerfstudio"):
        speedplus.read_camera(tmp_path)


@pytest.mark.parametrize("fields,words", [
    ({"Nu": 240.5}, "'Nu' must be a positive whole number"),
    ({"cameraMatrix": [[300.0, 1.0, 119.5], [0.0, 300.0, 74.5], [0.0, 0.0, 1.0]]}, "without skew"),
    ({"cameraMatrix": [[300.0, 0.0], [0.0, 300.0]]}, "'cameraMatrix' must be a 3x3 matrix"),
    ({"distCoeffs": [0.1, 0.2, 0.3]}, "'distCoeffs' must be 4, 5, 8, 12 or 14 numbers"),
])
def test_bad_camera_json_names_the_field(tmp_path, fields, words):
    _camera(tmp_path / "camera.json", **fields)
    with pytest.raises(DataFileError, match=words) as caught:
        read_camera(tmp_path / "camera.json")
    assert str(tmp_path / "camera.json") in str(caught.value) and "\n" not in str(caught.value)


def test_labels_give_the_pose_and_refuse_speed_v1_files(tmp_path):
    path = tmp_path / "labels.json"
    q, r = [0.5, 0.5, -0.5, 0.5], [0.1, -0.2, 7.0]
    path.write_text(json.dumps([{"filename": "a.jpg", "q_vbs2tango_true": q, "r_Vo2To_vbs_true": r}]))
    ((name, c2w),) = read_label_poses(path)
    assert name == "a.jpg"
    np.testing.assert_array_equal(c2w, opencv_to_opengl(label_to_c2w_opencv(np.array(q), np.array(r))))
    path.write_text(json.dumps([{"filename": "a.jpg", "q_vbs2tango": q, "r_Vo2To_vbs_true": r}]))
    with pytest.raises(DataFileError, match="label 0 in .* lacks 'q_vbs2tango_true'.*SPEED v1 label"):
        read_labels(path)
    path.write_text(json.dumps([{"filename": "a.jpg", "q_vbs2tango_true": [0, 0, 0, 0], "r_Vo2To_vbs_true": r}]))
    with pytest.raises(DataFileError, match="all zeros"):
        read_labels(path)


def test_images_are_rgb_over_black_in_both_forms(tmp_path):
    rng = np.random.default_rng(0)
    bgra = rng.integers(0, 65536, size=(6, 7, 4)).astype(np.uint16)
    bgra[0, 0, 3], bgra[0, 1, 3] = 0, 65535
    cv2.imwrite(str(tmp_path / "deep.png"), bgra)
    floats = read_rgb_over_black(tmp_path / "deep.png", np.float64)
    expected = bgra[..., 2::-1] / 65535.0 * (bgra[..., 3:] / 65535.0)
    np.testing.assert_allclose(floats, expected, rtol=1e-12)
    assert np.all(floats[0, 0] == 0) and read_rgb_over_black(tmp_path / "deep.png").dtype == np.float32
    assert np.array_equal(read_rgb8(tmp_path / "deep.png"), np.round(expected * 255).astype(np.uint8))
    grey_alpha = rng.integers(0, 256, size=(5, 4, 2)).astype(np.uint8)
    Image.fromarray(grey_alpha, "LA").save(tmp_path / "la.png")
    rgb = read_rgb8(tmp_path / "la.png")
    composited = np.round(grey_alpha[..., 0] * (grey_alpha[..., 1] / 255.0)).astype(np.uint8)
    assert rgb.shape == (5, 4, 3) and all(np.array_equal(rgb[..., c], composited) for c in range(3))
    plain = rng.integers(0, 256, size=(5, 4, 3)).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "plain.png"), plain)
    assert np.array_equal(read_rgb8(tmp_path / "plain.png"), plain[..., ::-1])
    (tmp_path / "broken.png").write_bytes(b"not an image")
    with pytest.raises(ImageError, match="cannot decode image .*broken.png"):
        read_rgb8(tmp_path / "broken.png")
    with pytest.raises(FileNotFoundError):
        read_rgb8(tmp_path / "missing.png")
