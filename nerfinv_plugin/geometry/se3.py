"""SE(3) in torch: exponential and logarithm of screw coordinates, perturbations about a point.

Screw coordinates follow the thesis (eq. 6) and Lynch & Park: a 6-vector ``xi = [w, v] * theta`` with the
angular part first. ``exp(xi)`` is the 4x4 rigid transform ``[[exp([w]theta), K v], [0, 1]]`` with
``K = I theta + (1 - cos theta)[w] + (theta - sin theta)[w]^2`` for unit ``w``; written here for
unnormalised ``w`` so that the map is smooth at zero, where the Taylor branches take over.
"""

import math

import torch
from torch import Tensor

_SMALL = 1e-3
"""Below this angle (radians) the trigonometric ratios use their Taylor series: their closed forms lose
all precision to cancellation near zero, and their gradients become NaN at exactly zero."""


def hat(w: Tensor) -> Tensor:
    """Skew-symmetric matrices [..., 3, 3] of vectors [..., 3]: ``hat(a) @ b == cross(a, b)``."""
    zero = torch.zeros_like(w[..., 0])
    return torch.stack([
        torch.stack([zero, -w[..., 2], w[..., 1]], -1),
        torch.stack([w[..., 2], zero, -w[..., 0]], -1),
        torch.stack([-w[..., 1], w[..., 0], zero], -1),
    ], -2)


def _ratios(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``sin(t)/t, (1-cos t)/t^2, (t-sin t)/t^3`` of ``t = sqrt(theta2)``, exact and smooth at 0."""
    small = theta2 < _SMALL**2
    t2 = torch.where(small, torch.ones_like(theta2), theta2)  # keeps the unused branch finite
    t = torch.sqrt(t2)
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(t)) / t2)
    c = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def exp_se3(xi: Tensor) -> Tensor:
    """Rigid transforms [..., 4, 4] of screw coordinates ``xi = [w, v]`` [..., 6] (angular part first)."""
    w, v = xi[..., :3], xi[..., 3:]
    big_w = hat(w)
    big_w2 = big_w @ big_w
    a, b, c = _ratios((w * w).sum(-1))
    a, b, c = a[..., None, None], b[..., None, None], c[..., None, None]
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(big_w.shape)
    rot = eye + a * big_w + b * big_w2
    k = eye + b * big_w + c * big_w2
    top = torch.cat([rot, (k @ v[..., None])], -1)
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def rotmat_to_quat(rot: Tensor) -> Tensor:
    """Unit quaternions [..., 4] (w, x, y, z), w >= 0, of rotation matrices [..., 3, 3]; stable at every
    angle (each element picks the best-conditioned of Shepperd's four formulas)."""
    m = rot
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = torch.stack([
        torch.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                     m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                     m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0],
                     1 + m[..., 1, 1] - m[..., 0, 0] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                     1 + m[..., 2, 2] - m[..., 0, 0] - m[..., 1, 1]], -1),
    ], -2)  # [..., 4, 4]: row k is 4 q_k q for the k-th component, largest norm is best conditioned
    best = candidates.norm(dim=-1).argmax(-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def log_so3(rot: Tensor) -> Tensor:
    """Rotation vectors [..., 3] (axis times angle in [0, pi]) of rotation matrices [..., 3, 3]."""
    q = rotmat_to_quat(rot)
    sin_half = q[..., 1:].norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(sin_half, q[..., :1])
    # angle / sin(angle / 2) -> 2 as the angle -> 0
    scale = torch.where(sin_half < 1e-7, 2.0 / q[..., :1].clamp_min(1e-12), angle / sin_half.clamp_min(1e-12))
    return q[..., 1:] * scale


def log_se3(transform: Tensor) -> Tensor:
    """Screw coordinates [..., 6] ``[w, v]`` of rigid transforms [..., 4, 4] (inverse of :func:`exp_se3`
    for rotation angles below pi)."""
    w = log_so3(transform[..., :3, :3])
    t = transform[..., :3, 3]
    theta2 = (w * w).sum(-1)
    a, b, _ = _ratios(theta2)
    small = theta2 < _SMALL**2
    # K^-1 = I - W/2 + g W^2 with g = (1 - a / (2 b)) / theta^2 -> 1/12 at zero
    g = torch.where(small, 1 / 12 + theta2 / 720, (1 - a / (2 * b)) / torch.where(small, 1.0, theta2))
    big_w = hat(w)
    eye = torch.eye(3, dtype=transform.dtype, device=transform.device)
    k_inv = eye - 0.5 * big_w + g[..., None, None] * (big_w @ big_w)
    return torch.cat([w, (k_inv @ t[..., None])[..., 0]], -1)


def rotation_about(point: Tensor, rot: Tensor) -> Tensor:
    """Rigid transforms [..., 4, 4] that rotate by ``rot`` [..., 3, 3] about ``point`` [3] (fixed)."""
    out = torch.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
    out[..., :3, :3] = rot
    out[..., :3, 3] = point - (rot @ point[..., None])[..., 0]
    out[..., 3, 3] = 1
    return out


def euler_xyz(angles: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of Euler angles [..., 3] (phi, theta, psi) in radians, applied about
    x, then y, then z: ``R = Rz(psi) Ry(theta) Rx(phi)``."""
    c, s = torch.cos(angles), torch.sin(angles)
    one, zero = torch.ones_like(c[..., 0]), torch.zeros_like(c[..., 0])
    rx = torch.stack([one, zero, zero, zero, c[..., 0], -s[..., 0], zero, s[..., 0], c[..., 0]], -1)
    ry = torch.stack([c[..., 1], zero, s[..., 1], zero, one, zero, -s[..., 1], zero, c[..., 1]], -1)
    rz = torch.stack([c[..., 2], -s[..., 2], zero, s[..., 2], c[..., 2], zero, zero, zero, one], -1)
    shape = (*angles.shape[:-1], 3, 3)
    return rz.reshape(shape) @ ry.reshape(shape) @ rx.reshape(shape)


def perturb_about(c2w: Tensor, centre: Tensor, max_rot_deg: float, max_trans: float,
                  generator: torch.Generator) -> Tensor:
    """Random copies of camera-to-world poses [N, 4, 4]: each rotated about ``centre`` (the target, so it
    stays in view) by Euler angles drawn from [-max_rot_deg, max_rot_deg], then moved by a translation
    drawn from [-max_trans, max_trans] per world axis (model units)."""
    n = c2w.shape[0]
    angles = (torch.rand(n, 3, generator=generator, dtype=c2w.dtype) * 2 - 1) * math.radians(max_rot_deg)
    shift = (torch.rand(n, 3, generator=generator, dtype=c2w.dtype) * 2 - 1) * max_trans
    moved = rotation_about(centre.to(c2w), euler_xyz(angles).to(c2w)) @ c2w
    moved[:, :3, 3] += shift.to(c2w)
    return moved


def geodesic_deg(rot_a: Tensor, rot_b: Tensor) -> Tensor:
    """Angle in degrees of the rotation between ``rot_a`` and ``rot_b`` [..., 3, 3]; accurate near 0 and
    pi (atan2 of the rotation's sine and cosine parts, never arccos of a clamped trace)."""
    rel = rot_a.transpose(-1, -2) @ rot_b
    cos = (rel[..., 0, 0] + rel[..., 1, 1] + rel[..., 2, 2] - 1) / 2
    sin_vec = torch.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0],
                           rel[..., 1, 0] - rel[..., 0, 1]], -1) / 2
    return torch.rad2deg(torch.atan2(sin_vec.norm(dim=-1), cos))
