"""Pose errors in the dataset's metric frame, and the SPEC2021 pose score used by SPEED+ and SHIRT."""

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.geometry.frames import quat_wxyz_to_rotmat
from nerfinv_plugin.geometry.se3 import geodesic_deg

HIL_ROTATION_THRESHOLD_DEG = 0.169
"""Below this rotation error the SPEC2021 score counts 0 on the lightbox and sunlamp domains."""
HIL_TRANSLATION_THRESHOLD = 2.173e-3
"""Below this normalised translation error (m/m) the score counts 0 on lightbox and sunlamp."""


def rotation_error_deg(c2w: Tensor, truth: Tensor) -> Tensor:
    """Degrees between the attitudes of the poses ``c2w`` [..., 4, 4] and the true pose ``truth`` [4, 4]
    (or one per pose, [..., 4, 4]). The same in the model and the dataset frame: they are one rotation
    (and a scale) apart, and a scale turns no attitude."""
    rotations = c2w[..., :3, :3]
    return geodesic_deg(rotations, truth[..., :3, :3].to(rotations).expand_as(rotations))


@dataclass(frozen=True)
class PoseError:
    rotation_deg: float
    """Geodesic angle between the estimated and true attitudes."""
    translation_m: float
    """Distance between the estimated and true target positions in the camera frame."""
    translation_rel: float
    """``translation_m`` over the true range (SPEC2021's e_t)."""
    score: float
    """SPEC2021 pose score: rotation error in radians plus ``translation_rel``."""


def label_error(q_est: np.ndarray, r_est: np.ndarray, q_true: np.ndarray, r_true: np.ndarray,
                hil: bool = False) -> PoseError:
    """Errors of an estimated SHIRT/SPEED+ label (scalar-first quaternion, target position in the camera
    frame, metres) against the truth. ``hil`` applies the lightbox/sunlamp thresholds to the score."""
    rot_est, rot_true = (torch.as_tensor(quat_wxyz_to_rotmat(q)) for q in (q_est, q_true))
    rotation_deg = float(geodesic_deg(rot_est, rot_true))
    r_est, r_true = np.asarray(r_est, dtype=np.float64), np.asarray(r_true, dtype=np.float64)
    translation_m = float(np.linalg.norm(r_est - r_true))
    translation_rel = translation_m / float(np.linalg.norm(r_true))
    e_q = 0.0 if hil and rotation_deg < HIL_ROTATION_THRESHOLD_DEG else np.radians(rotation_deg)
    e_t = 0.0 if hil and translation_rel < HIL_TRANSLATION_THRESHOLD else translation_rel
    return PoseError(rotation_deg, translation_m, translation_rel, float(e_q + e_t))
