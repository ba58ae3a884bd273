"""Camera poses: training views around an object, and SHIRT-like rendezvous trajectories.

A trajectory is produced as object-to-camera transforms, the way SHIRT labels describe it (the servicer's
camera sees the target's body frame), and converted to camera-to-body poses for rendering.
"""

from dataclasses import dataclass, fields
from typing import Literal

import numpy as np

from nerfinv_plugin.geometry.frames import look_at_c2w_opencv, quat_wxyz_to_rotmat


def _axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues' formula: rotation by ``angle_rad`` about the unit ``axis``."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * (k @ k)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed rotation (a normalised Gaussian quaternion is uniform on the 3-sphere)."""
    return quat_wxyz_to_rotmat(rng.standard_normal(4))


def orbit_views(num: int, range_m: float, range_jitter: float, centre: np.ndarray,
                rng: np.random.Generator) -> np.ndarray:
    """Camera-to-world poses (OpenCV axes) spread evenly over a sphere around ``centre``, each looking at
    it with a random roll, at a range drawn from ``range_m * (1 +- range_jitter)``. Returns [num, 4, 4].

    A Fibonacci lattice with a random global rotation covers the sphere without clumps, so every side of
    the object is seen in training.
    """
    i = np.arange(num) + 0.5
    polar = np.arccos(1 - 2 * i / num)
    azimuth = np.pi * (1 + 5**0.5) * i
    dirs = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)
    dirs = dirs @ random_rotation(rng).T
    poses = np.empty((num, 4, 4))
    for k, d in enumerate(dirs):
        distance = range_m * (1 + range_jitter * rng.uniform(-1, 1))
        poses[k] = look_at_c2w_opencv(centre + distance * d, centre, roll=rng.uniform(-np.pi, np.pi))
    return poses


TrajectoryKind = Literal["roe1", "roe2"]


@dataclass
class TrajectoryMotion:
    """Relative motion of a SHIRT-like trajectory. Rates are per second; ``frame_spacing_s`` turns them
    into per-frame steps (SHIRT images are 5 s apart)."""

    num_frames: int = 20
    """Frames per trajectory."""
    frame_spacing_s: float = 5.0
    """Seconds between frames (SHIRT uses 5 s)."""
    range_m: float = 5.0
    """roe1: constant camera-target range; roe2: range at the first frame (metres)."""
    end_range_m: float = 4.0
    """roe2: range at the last frame (metres)."""
    spin_rate_deg_s: float = 0.8
    """Spin rate about the body z axis (degrees per second; 0.8 at 5 s spacing is 4 degrees a frame)."""
    second_rate_deg_s: float = 0.5
    """roe2: tumble rate about the body x axis (degrees per second)."""


@dataclass
class TrajectorySpec(TrajectoryMotion):
    """A trajectory kind with its motion: roe1 holds a constant range while the target spins about its z
    axis; roe2 approaches slowly while the target tumbles about its z and x axes."""

    kind: TrajectoryKind = "roe1"

    @classmethod
    def of(cls, kind: TrajectoryKind, motion: TrajectoryMotion) -> "TrajectorySpec":
        return cls(**{f.name: getattr(motion, f.name) for f in fields(TrajectoryMotion)}, kind=kind)


def trajectory_object_to_camera(spec: TrajectorySpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame rotation [F, 3, 3] and translation [F, 3] mapping body points into the camera frame
    (OpenCV axes, metres): ``X_cam = R X_body + r``, exactly what a SHIRT label encodes.

    The starting attitude is random (seeded). A principal-axis spin keeps its axis fixed in both frames,
    so spinning is a right-multiplication by a rotation about a body axis.
    """
    if spec.num_frames < 1:
        raise ValueError(f"a trajectory needs at least one frame, got num_frames={spec.num_frames}")
    start = random_rotation(rng)
    t = np.arange(spec.num_frames) * spec.frame_spacing_s
    z_axis, x_axis = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    rotations = np.empty((spec.num_frames, 3, 3))
    translations = np.zeros((spec.num_frames, 3))
    if spec.kind == "roe1":
        for k, tk in enumerate(t):
            rotations[k] = start @ _axis_angle(z_axis, np.radians(spec.spin_rate_deg_s * tk))
        translations[:, 2] = spec.range_m
    elif spec.kind == "roe2":
        progress = t / max(t[-1], 1e-12)
        for k, tk in enumerate(t):
            rotations[k] = (start @ _axis_angle(z_axis, np.radians(spec.spin_rate_deg_s * tk))
                            @ _axis_angle(x_axis, np.radians(spec.second_rate_deg_s * tk)))
        ranges = spec.range_m + (spec.end_range_m - spec.range_m) * progress
        # The target drifts a little across the field of view as the approach closes in.
        translations[:, 0] = 0.04 * ranges * np.sin(2 * np.pi * progress)
        translations[:, 1] = 0.03 * ranges * np.cos(np.pi * progress)
        translations[:, 2] = ranges
    else:
        raise ValueError(f"unknown trajectory kind {spec.kind!r}; choose roe1 or roe2")
    return rotations, translations
