"""Conversions between SHIRT / SPEED+ pose labels and camera-to-world matrices.

Labels give the target body in the camera frame: ``X_cam = R(q) X_body + r`` with ``q`` scalar-first
(``q_vbs2tango_true``) and ``r`` the body origin in the camera frame in metres (``r_Vo2To_vbs_true``),
camera axes OpenCV (x right, y down, z along the boresight). The world frame is the target body frame,
so the camera-to-world pose is the inverse of the object-to-camera transform. nerfstudio wants OpenGL
camera axes (x right, y up, z back), which differ from OpenCV by a flip of y and z.

All functions are plain float64 numpy: this is the boundary where dataset numbers enter once.
"""

import numpy as np
import torch

from nerfinv_plugin.geometry.se3 import rotmat_to_quat

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera-to-world pose by this swaps OpenCV and OpenGL camera axes (it is its own
inverse)."""


def quat_wxyz_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Active rotation matrix of a scalar-first Hamilton quaternion; ``q`` need not be unit length."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_quat_wxyz(rot: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternion of a rotation matrix, with ``w >= 0``, stable at every angle."""
    return rotmat_to_quat(torch.as_tensor(np.asarray(rot, dtype=np.float64))).numpy()


def object_to_camera_to_c2w(rot: np.ndarray, r_cam: np.ndarray) -> np.ndarray:
    """Camera-to-body 4x4 pose (OpenCV camera axes) of ``X_cam = rot X_body + r_cam``."""
    rot = np.asarray(rot, dtype=np.float64)
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T
    c2w[:3, 3] = -rot.T @ np.asarray(r_cam, dtype=np.float64)
    return c2w


def label_to_c2w_opencv(q_wxyz: np.ndarray, r_cam: np.ndarray) -> np.ndarray:
    """Camera-to-body 4x4 pose (OpenCV camera axes) from a SHIRT / SPEED+ label."""
    return object_to_camera_to_c2w(quat_wxyz_to_rotmat(q_wxyz), r_cam)


def c2w_opencv_to_label(c2w_cv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`label_to_c2w_opencv`: ``(q_vbs2tango wxyz, r_Vo2To_vbs metres)``."""
    c2w_cv = np.asarray(c2w_cv, dtype=np.float64)
    rot = c2w_cv[:3, :3].T
    r_cam = -rot @ c2w_cv[:3, 3]
    return rotmat_to_quat_wxyz(rot), r_cam


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Swap the camera axes of a camera-to-world pose between OpenCV and OpenGL (works both ways)."""
    return np.asarray(c2w, dtype=np.float64) @ OPENCV_TO_OPENGL


def look_at_c2w_opencv(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None,
                       roll: float = 0.0) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) of a camera at ``eye`` whose boresight passes through
    ``target``, with image-up as close to ``up`` as possible (world z, or world y when looking almost
    along z, if not given), then turned by ``roll`` radians about the boresight (the target stays put)."""
    eye, target = (np.asarray(v, dtype=np.float64) for v in (eye, target))
    z = target - eye
    z /= np.linalg.norm(z)
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, np.asarray(up, dtype=np.float64))  # right = forward x up; image y then points down
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"up vector {up} is parallel to the viewing direction {z}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], 1) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    c2w[:3, 3] = eye
    return c2w
