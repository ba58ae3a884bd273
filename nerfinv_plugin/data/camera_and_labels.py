"""The two files SHIRT and SPEED+ share (/work/shared/reference/datasets.md), read and checked in one place:
``camera.json`` (OpenCV intrinsics and lens distortion of the images on disk) and the pose labels (the
target body in the camera frame: scalar-first quaternion, translation in metres).

Both the sequence reader of ``ns-invert`` and the ``speedplus-data`` dataparser read them here; each turns
:class:`DataFileError` into its own error type where its callers expect one. nerfstudio imports the
dataparser for every ``ns-*`` command, so this module imports nothing heavy.
"""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfinv_plugin.geometry.frames import label_to_c2w_opencv, opencv_to_opengl

LABEL_KEYS = ("filename", "q_vbs2tango_true", "r_Vo2To_vbs_true")
CAMERA_KEYS = ("Nu", "Nv", "cameraMatrix")
"""Required in camera.json; ``distCoeffs`` may be left out (no distortion)."""
DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
"""Numbers of distortion coefficients OpenCV accepts (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]])."""


class DataFileError(ValueError):
    """A camera.json or label file that does not hold what SHIRT / SPEED+ files hold; the message is one
    line that names the file and says how to fix it."""


@dataclass(frozen=True)
class CameraFile:
    """What camera.json says about the images on disk."""

    width: int
    """Nu, pixels."""
    height: int
    """Nv, pixels."""
    matrix: np.ndarray
    """[3, 3] OpenCV camera matrix (pixel centres at integer coordinates), no skew."""
    dist: np.ndarray
    """OpenCV distortion coefficients (k1, k2, p1, p2, ...), as many as the file gives (see DIST_LENGTHS)."""


def read_json(path: Path) -> object:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DataFileError(f"cannot read {path} ({err}); fix or regenerate the file") from err


def finite_array(value: object, shape: tuple[int, ...], where: str, expected: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` with finite entries, or a :class:`DataFileError` saying
    that ``where`` must be ``expected``."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = np.empty(0)
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise DataFileError(f"{where} must be {expected} of finite numbers, not {value!r}")
    return array


def read_camera(path: Path) -> CameraFile:
    """camera.json at ``path``, checked: whole positive Nu and Nv, a 3x3 finite matrix without skew, and a
    number of distortion coefficients that OpenCV takes."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise DataFileError(f"{path} must hold an object with Nu, Nv, cameraMatrix and distCoeffs; fix it")
    for key in CAMERA_KEYS:
        if key not in data:
            raise DataFileError(f"{path} has no {key!r}; a camera.json needs Nu, Nv, cameraMatrix (and distCoeffs)")
    for key in ("Nu", "Nv"):
        if not isinstance(data[key], int | float) or data[key] != int(data[key]) or data[key] <= 0:
            raise DataFileError(f"{path}: {key!r} must be a positive whole number of pixels, not {data[key]!r}")
    matrix = finite_array(data["cameraMatrix"], (3, 3), f"{path}: 'cameraMatrix'", "a 3x3 matrix")
    if matrix[0, 1] != 0:
        raise DataFileError(f"{path}: 'cameraMatrix' must be an OpenCV matrix without skew (entry [0][1] zero), "
                            f"got {matrix.tolist()}")
    try:
        dist = np.asarray(data.get("distCoeffs", []), dtype=np.float64).ravel()
    except (TypeError, ValueError):
        dist = np.full(1, np.nan)
    if dist.size not in DIST_LENGTHS or not np.all(np.isfinite(dist)):
        raise DataFileError(f"{path}: 'distCoeffs' must be 4, 5, 8, 12 or 14 numbers (OpenCV's k1 k2 p1 p2 ...), "
                            f"not {data.get('distCoeffs')!r}")
    return CameraFile(int(data["Nu"]), int(data["Nv"]), matrix, dist)


def read_labels(path: Path) -> list[dict]:
    """The labels of a SHIRT / SPEED+ label file in file order, each checked to have a filename, a
    non-zero quaternion and a 3-vector of finite numbers, so that a bad file fails here, naming the label."""
    labels = read_json(path)
    if not isinstance(labels, list):
        raise DataFileError(f"{path} must hold a list of labels with {', '.join(LABEL_KEYS)}; fix or regenerate it")
    for i, label in enumerate(labels):
        missing = [key for key in LABEL_KEYS if not isinstance(label, dict) or key not in label]
        if missing:
            v1 = " (a SPEED v1 label: rename 'q_vbs2tango' to 'q_vbs2tango_true')" if (
                isinstance(label, dict) and "q_vbs2tango" in label) else ""
            raise DataFileError(f"label {i} in {path} lacks {', '.join(map(repr, missing))}; every label needs "
                                f"filename, q_vbs2tango_true (scalar first) and r_Vo2To_vbs_true (metres){v1}")
        q = finite_array(label["q_vbs2tango_true"], (4,), f"label {i} in {path}: 'q_vbs2tango_true'", "a quaternion")
        finite_array(label["r_Vo2To_vbs_true"], (3,), f"label {i} in {path}: 'r_Vo2To_vbs_true'", "a 3-vector")
        if not np.any(q):
            raise DataFileError(f"label {i} in {path}: 'q_vbs2tango_true' is all zeros; give a unit quaternion")
    return labels


def label_c2w_opengl(label: dict) -> np.ndarray:
    """Camera-to-body pose [4, 4] of a label (from :func:`read_labels`), OpenGL camera axes, metres."""
    q = np.asarray(label["q_vbs2tango_true"], dtype=np.float64)
    r = np.asarray(label["r_Vo2To_vbs_true"], dtype=np.float64)
    return opencv_to_opengl(label_to_c2w_opencv(q, r))


def read_label_poses(path: Path) -> list[tuple[str, np.ndarray]]:
    """``(filename, camera-to-body pose with OpenGL axes)`` of every label in ``path``, in file order."""
    return [(str(label["filename"]), label_c2w_opengl(label)) for label in read_labels(path)]
