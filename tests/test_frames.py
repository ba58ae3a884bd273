"""Frame conversions at the dataset boundary, against scipy and closed forms."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nerfinv_plugin.geometry.frames import (
    c2w_opencv_to_label,
    label_to_c2w_opencv,
    look_at_c2w_opencv,
    opencv_to_opengl,
    quat_wxyz_to_rotmat,
    rotmat_to_quat_wxyz,
)


def _random_quats(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_quaternion_matrix_matches_scipy_scalar_first():
    for q in _random_quats(50):
        expected = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        np.testing.assert_allclose(quat_wxyz_to_rotmat(q), expected, atol=1e-12)


@pytest.mark.parametrize("angle_deg", [0.0, 1e-6, 90.0, 179.999, 180.0])
def test_matrix_to_quaternion_round_trip_small_and_near_pi(angle_deg):
    for axis in np.random.default_rng(1).standard_normal((10, 3)):
        rot = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis))
        q = rotmat_to_quat_wxyz(rot.as_matrix())
        x, y, z, w = rot.as_quat()
        expected = np.array([w, x, y, z]) * (1 if w >= 0 else -1)
        # At exactly 180 degrees w = 0 and q, -q are both valid: compare up to sign.
        assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-9
        np.testing.assert_allclose(quat_wxyz_to_rotmat(q), rot.as_matrix(), atol=1e-9)


def test_label_pose_maps_body_points_like_the_official_projection():
    """X_cam = R(q) X_body + r (SPEED+'s ``project_keypoints``) must equal inverse(c2w) applied to X."""
    rng = np.random.default_rng(2)
    for q in _random_quats(20, seed=3):
        r = rng.uniform([-1, -1, 3], [1, 1, 9])
        c2w = label_to_c2w_opencv(q, r)
        points = rng.standard_normal((5, 3))
        expected = points @ Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix().T + r
        homog = np.c_[points, np.ones(5)] @ np.linalg.inv(c2w).T
        np.testing.assert_allclose(homog[:, :3], expected, atol=1e-10)
        q_back, r_back = c2w_opencv_to_label(c2w)
        np.testing.assert_allclose(r_back, r, atol=1e-10)
        assert min(np.abs(q_back - q).max(), np.abs(q_back + q).max()) < 1e-10


def test_opencv_opengl_flip_is_an_involution_and_flips_y_z():
    c2w = label_to_c2w_opencv(_random_quats(1)[0], [0.1, -0.2, 5.0])
    gl = opencv_to_opengl(c2w)
    np.testing.assert_allclose(gl[:3, 0], c2w[:3, 0])
    np.testing.assert_allclose(gl[:3, 1:3], -c2w[:3, 1:3])
    np.testing.assert_allclose(opencv_to_opengl(gl), c2w)


def test_look_at_centres_the_target_with_up_at_the_top():
    eye, target, up = np.array([3.0, -4.0, 1.0]), np.array([0.2, 0.1, 0.3]), np.array([0.0, 0.0, 1.0])
    c2w = look_at_c2w_opencv(eye, target, up)
    np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
    in_cam = np.linalg.inv(c2w) @ np.r_[target, 1.0]
    np.testing.assert_allclose(in_cam[:2], 0.0, atol=1e-12)  # on the boresight
    above = np.linalg.inv(c2w) @ np.r_[target + up, 1.0]
    assert above[1] < 0  # OpenCV y points down: a point above the target is at negative y
