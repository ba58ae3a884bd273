"""nerfstudio's scene contraction with the infinity norm (nerfacto's), computed as a max of absolute values.

``torch.linalg.norm(x, ord=inf)`` takes a slow general path on the CPU: about a tenth of an inversion
iteration once the hash grids are compiled (docs/benchmarks.md). ``x.abs().amax(-1)`` is the same number
with the same gradient, in half the time. Gaussians (mip-NeRF style) and other norms keep nerfstudio's code.
"""

import math
import types

import torch
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.utils.math import Gaussians
from torch import Tensor


def max_norm_contraction(self: SceneContraction, positions: Tensor | Gaussians) -> Tensor | Gaussians:
    if isinstance(positions, Gaussians) or not math.isinf(float(self.order or 2)):
        return type(self).forward(self, positions)
    unit = getattr(self, "unit", None)  # nerfacto-tiny measures positions in a unit fitted to its cameras
    if unit is not None:
        positions = positions / unit
    mag = positions.abs().amax(-1, keepdim=True)
    return torch.where(mag < 1, positions, (2 - (1 / mag)) * (positions / mag))


def use_max_norm_contraction(module: torch.nn.Module) -> int:
    """Switch every ``SceneContraction`` inside ``module`` to :func:`max_norm_contraction`; returns how many."""
    count = 0
    for sub in module.modules():
        if isinstance(sub, SceneContraction):
            sub.forward = types.MethodType(max_norm_contraction, sub)
            count += 1
    return count
