"""SE(3) maps against scipy and closed forms, at ordinary angles, near zero and near pi."""

import math

import numpy as np
import pytest
import torch
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from nerfinv_plugin.geometry.se3 import (
    euler_xyz,
    exp_se3,
    geodesic_deg,
    hat,
    log_se3,
    log_so3,
    perturb_about,
    rotmat_to_quat,
)


def _screws(angles: list[float], seed: int = 0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    rows = []
    for angle in angles:
        axis = rng.normal(size=3)
        rows.append(np.r_[angle * axis / np.linalg.norm(axis), rng.normal(size=3)])
    return torch.as_tensor(np.array(rows), dtype=torch.float64)


ANGLES = [0.0, 1e-9, 1e-5, 2e-3, 0.3, 1.5, 3.0, math.pi - 1e-6]


def test_exp_matches_matrix_exponential_of_the_twist():
    xi = _screws(ANGLES)
    ours = exp_se3(xi).numpy()
    for row, got in zip(xi.numpy(), ours):
        twist = np.zeros((4, 4))
        twist[:3, :3] = hat(torch.as_tensor(row[:3])).numpy()
        twist[:3, 3] = row[3:]
        np.testing.assert_allclose(got, expm(twist), atol=1e-10)
        np.testing.assert_allclose(got[:3, :3], Rotation.from_rotvec(row[:3]).as_matrix(), atol=1e-10)


def test_log_inverts_exp_including_tiny_and_near_pi_angles():
    xi = _screws(ANGLES[:-1] + [math.pi - 1e-4])
    np.testing.assert_allclose(log_se3(exp_se3(xi)).numpy(), xi.numpy(), atol=1e-7)
    transforms = exp_se3(_screws([0.0, 0.7, 2.9], seed=1))
    np.testing.assert_allclose(exp_se3(log_se3(transforms)).numpy(), transforms.numpy(), atol=1e-10)


def test_log_so3_and_quaternions_match_scipy():
    rotations = Rotation.from_rotvec(_screws(ANGLES, seed=2)[:, :3].numpy())
    rot = torch.as_tensor(rotations.as_matrix())
    np.testing.assert_allclose(log_so3(rot).norm(dim=-1).numpy(), rotations.magnitude(), atol=1e-7)
    q = rotmat_to_quat(rot).numpy()
    x, y, z, w = rotations.as_quat().T
    expected = np.stack([w, x, y, z], 1) * np.where(w < 0, -1, 1)[:, None]
    assert np.minimum(np.abs(q - expected).max(1), np.abs(q + expected).max(1)).max() < 1e-7


def test_exp_has_finite_exact_gradients_at_and_near_zero():
    for scale in (0.0, 1e-6, 0.5):
        xi = (scale * _screws([1.0], seed=3)).requires_grad_(True)
        assert torch.autograd.gradcheck(exp_se3, (xi,), eps=1e-7, atol=1e-6)


def test_geodesic_angle_matches_scipy_near_zero_and_pi():
    rng = np.random.default_rng(4)
    for angle_deg in (0.0, 1e-4, 0.5, 90.0, 179.9, 180.0):
        base = Rotation.random(random_state=rng)
        axis = rng.normal(size=3)
        rel = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis))
        a, b = (torch.as_tensor(r.as_matrix()) for r in (base, base * rel))
        assert float(geodesic_deg(a, b)) == pytest.approx(np.degrees(rel.magnitude()), abs=1e-6)


def test_euler_order_and_perturbation_about_a_centre():
    angles = torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64)
    expected = Rotation.from_euler("xyz", angles[0].numpy()).as_matrix()  # extrinsic x, y, z
    np.testing.assert_allclose(euler_xyz(angles)[0].numpy(), expected, atol=1e-12)
    c2w = torch.eye(4, dtype=torch.float64).repeat(200, 1, 1)
    c2w[:, :3, 3] = torch.tensor([0.3, -0.2, 5.0], dtype=torch.float64)
    centre = torch.tensor([0.1, 0.1, 0.2], dtype=torch.float64)
    moved = perturb_about(c2w, centre, max_rot_deg=20.0, max_trans=0.0, generator=torch.Generator().manual_seed(0))
    before = (c2w[:, :3, 3] - centre).norm(dim=-1)
    after = (moved[:, :3, 3] - centre).norm(dim=-1)
    torch.testing.assert_close(after, before)  # rotating about the centre keeps the range
    # The centre keeps its place in the image: its camera-frame coordinates do not change.
    in_cam = lambda t: (torch.linalg.inv(t) @ torch.cat([centre, torch.ones(1, dtype=t.dtype)]))[:, :3]  # noqa: E731
    torch.testing.assert_close(in_cam(moved), in_cam(c2w))
    angles_deg = geodesic_deg(c2w[:, :3, :3], moved[:, :3, :3])
    assert angles_deg.max() <= 20.0 * math.sqrt(3) + 1e-9 and angles_deg.max() > 15.0
    shifted = perturb_about(c2w, centre, 0.0, 0.1, torch.Generator().manual_seed(1))
    offsets = shifted[:, :3, 3] - c2w[:, :3, 3]
    assert offsets.abs().max() <= 0.1 and offsets.abs().max() > 0.09
