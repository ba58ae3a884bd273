"""Pose errors and the SPEC2021 score against hand-computed cases and the official formula."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nerfinv_plugin.geometry.errors import label_error


def _wxyz(rot: Rotation) -> np.ndarray:
    x, y, z, w = rot.as_quat()
    return np.array([w, x, y, z])


def test_hand_computed_errors_and_score():
    truth = Rotation.from_euler("xyz", [20, -35, 70], degrees=True)
    estimate = truth * Rotation.from_euler("z", 10, degrees=True)
    error = label_error(_wxyz(estimate), [0.3, 0.0, 6.0], _wxyz(truth), [0.0, 0.0, 6.0])
    assert error.rotation_deg == pytest.approx(10.0, abs=1e-9)
    assert error.translation_m == pytest.approx(0.3) and error.translation_rel == pytest.approx(0.05)
    assert error.score == pytest.approx(np.radians(10.0) + 0.05)
    # The official e_q = 2 arccos(|<q_est, q_true>|), insensitive to the quaternion's sign.
    official = 2 * np.arccos(min(1.0, abs(np.dot(-_wxyz(estimate), _wxyz(truth)))))
    assert np.radians(error.rotation_deg) == pytest.approx(official, abs=1e-9)


def test_hil_thresholds_zero_small_errors_only_when_asked():
    truth = Rotation.from_euler("y", 40, degrees=True)
    estimate = truth * Rotation.from_euler("x", 0.1, degrees=True)
    r_true, r_est = np.array([0.2, -0.1, 8.0]), np.array([0.2, -0.1, 8.01])  # e_t = 1.25e-3
    assert label_error(_wxyz(estimate), r_est, _wxyz(truth), r_true, hil=True).score == 0.0
    synthetic = label_error(_wxyz(estimate), r_est, _wxyz(truth), r_true)
    assert synthetic.score == pytest.approx(np.radians(0.1) + 0.01 / np.linalg.norm(r_true), rel=1e-6)
