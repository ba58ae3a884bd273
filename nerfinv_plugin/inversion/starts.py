"""Where the first Monte Carlo step starts: candidate camera poses in the dataset frame (OpenGL axes,
metres), for :meth:`LoadedModel.dataset_to_model` to map into the model. All seeded.

- ``training_views``: the poses of the training images (the thesis' default);
- ``drawn_from``: poses drawn from a given set (the thesis' SHIRT runs drew them from SHIRT labels);
- ``sphere_shell``: cameras at one range looking at the target with random roll (the same-range case of
  the thesis' section 5.3.1);
- ``volume``: cameras anywhere up to a maximum range (SPEED+-like, section 5.3.2);
- ``around_prior``: a known approximate pose plus noise;
- ``inerf_protocol_starts``: model-frame poses a given angle range away from a true pose (for tests and
  benchmarks, as iNeRF evaluates).
"""

import json
from pathlib import Path

import numpy as np
import torch

from nerfinv_plugin.geometry.frames import look_at_c2w_opencv, opencv_to_opengl
from nerfinv_plugin.geometry.se3 import exp_se3, perturb_about, rotation_about


def training_views(transforms_json: Path, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` poses [count, 4, 4] drawn without replacement from a Blender or nerfstudio transforms
    file (all of them when it has fewer)."""
    frames = json.loads(Path(transforms_json).read_text())["frames"]
    return drawn_from(np.array([frame["transform_matrix"] for frame in frames], dtype=np.float64), count, rng)


def drawn_from(poses: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` of ``poses`` [M, 4, 4] drawn without replacement, in their order (all when M <= count)."""
    pick = rng.choice(len(poses), size=min(count, len(poses)), replace=False)
    return poses[np.sort(pick)]


def _looking_at(eyes: np.ndarray, target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """OpenGL camera-to-world poses at ``eyes`` looking at ``target``, each with a random roll."""
    return np.array([opencv_to_opengl(look_at_c2w_opencv(eye, target, roll=rng.uniform(-np.pi, np.pi)))
                     for eye in eyes])


def _unit_vectors(count: int, rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def sphere_shell(count: int, range_m: float, target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Cameras uniformly on the sphere of radius ``range_m`` around ``target``, looking at it, random roll."""
    return _looking_at(target + range_m * _unit_vectors(count, rng), target, rng)


def volume(count: int, max_range_m: float, min_range_m: float, target: np.ndarray,
           rng: np.random.Generator) -> np.ndarray:
    """Cameras uniformly distributed in the volume between ``min_range_m`` and ``max_range_m`` around
    ``target`` (uniform in volume, so most are far), looking at it, random roll."""
    u = rng.uniform(min_range_m**3, max_range_m**3, size=count)
    return _looking_at(target + np.cbrt(u)[:, None] * _unit_vectors(count, rng), target, rng)


def around_prior(prior: np.ndarray, count: int, rot_deg: float, trans_m: float, target: np.ndarray,
                 seed: int) -> np.ndarray:
    """``count`` copies of ``prior`` [4, 4] turned about ``target`` by Euler angles within ``rot_deg`` and
    shifted within ``trans_m`` per axis (the first copy is the prior itself)."""
    poses = torch.as_tensor(np.asarray(prior, dtype=np.float64)).repeat(count, 1, 1)
    noisy = perturb_about(poses, torch.as_tensor(target, dtype=torch.float64), rot_deg, trans_m,
                          torch.Generator().manual_seed(seed)).numpy()
    noisy[0] = prior
    return noisy


def inerf_protocol_starts(truth: torch.Tensor, centre: torch.Tensor, count: int, min_deg: float, max_deg: float,
                          shift: float, seed: int) -> torch.Tensor:
    """``count`` poses turned about ``centre`` by ``min_deg``-``max_deg`` about random axes and moved by
    ``shift`` (model units) in random directions: iNeRF's evaluation protocol."""
    g = torch.Generator().manual_seed(seed)
    axes = torch.randn(count, 3, generator=g)
    axes /= axes.norm(dim=-1, keepdim=True)
    angles = torch.deg2rad(min_deg + (max_deg - min_deg) * torch.rand(count, generator=g))
    rot = exp_se3(torch.cat([axes * angles[:, None], torch.zeros(count, 3)], 1))[:, :3, :3]
    out = rotation_about(centre, rot) @ truth[None].repeat(count, 1, 1)
    direction = torch.randn(count, 3, generator=g)
    out[:, :3, 3] += direction / direction.norm(dim=-1, keepdim=True) * shift
    return out
