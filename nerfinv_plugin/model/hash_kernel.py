"""A compiled CPU kernel for hash-grid encodings whose tables are frozen, as they are during inversion.

Inverting a model spends most of its CPU time in the hash encodings (docs/benchmarks.md): the torch
forward, even fused, runs a dozen tensor operations per level whose intermediates ([rays x samples x
levels x 8] indices, weights and features) go through memory, and autograd records all of them for a
backward that only needs the gradient with respect to the positions. ``hash_grid.cpp`` does the same
arithmetic in one pass per point and level; where the positions need a gradient, that pass also writes
the features' Jacobian with respect to them ([points, levels x features, 3]: for nerfacto-tiny's field 48
floats a sample), so the backward is one contraction and reads no table row again. It runs on torch's
intra-op threads (built with OpenMP, it shares the libgomp torch loaded). It is built with torch's C++
extension loader the first time it is needed (about 30 s; then cached by torch under
``~/.cache/torch_extensions``), and used only where it computes what nerfstudio computes (to float
rounding): float32 positions on the CPU and a table that does not require gradients. Anything
else (training, CUDA, double precision) goes through :func:`fused_hash_forward`.

The same extension evaluates nerfacto's proposal networks whole (:func:`kernel_density_fn`): contraction, hash
grid, MLP and activation in one pass per sample, forward only, since inversion evaluates them without
gradients (nerfacto does, once trained); in torch they took a fifth of an iteration.

Set ``NERFINV_HASH_KERNEL=0`` to never build or use it. Where it cannot be built (no C++ compiler), a
warning says so once and the torch forward is used.
"""

import functools
import hashlib
import logging
import math
import os
import types
import warnings
from collections.abc import Callable
from pathlib import Path

import torch
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.mlp import MLP
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.fields.density_fields import HashMLPDensityField
from torch import Tensor

from nerfinv_plugin.model.fused_hash import fused_hash_forward, use_fused_hash_encoding

SOURCE = Path(__file__).with_name("hash_grid.cpp")


def enabled() -> bool:
    return os.environ.get("NERFINV_HASH_KERNEL", "1") != "0"


@functools.cache
def extension() -> types.ModuleType | None:
    """The built kernel, or ``None`` (with one warning) where it cannot be built or is turned off."""
    if not enabled():
        return None
    # Importing the loader on a machine without CUDA logs a warning about CUDA_HOME that does not concern a
    # CPU kernel.
    logging.getLogger("torch.utils.cpp_extension").setLevel(logging.ERROR)
    from torch.utils.cpp_extension import load

    # -fopenmp: at::parallel_for runs its whole range on one thread in code compiled without it. The extension
    # then uses the libgomp torch has already loaded (same soname), so torch's thread count applies. A
    # compiler without OpenMP (Apple's clang) still gets the kernel, on one thread.
    failure = None
    for flags in (["-O3", "-fopenmp"], ["-O3"]):
        # The source and flags hashed into the name: an edited kernel is rebuilt, never loaded stale.
        digest = hashlib.sha256(SOURCE.read_bytes() + " ".join(flags).encode()).hexdigest()[:12]
        try:
            return load(name=f"nerfinv_hash_grid_{digest}", sources=[str(SOURCE)], extra_cflags=flags,
                        extra_ldflags=flags[1:], verbose=False)
        except Exception as err:  # noqa: BLE001 - a missing compiler, headers or ninja all mean the same here
            failure = err
    first = (str(failure).strip().splitlines() or [""])[-1][:200]
    warnings.warn(f"nerfinv: the compiled hash-grid kernel could not be built ({type(failure).__name__}: {first}); "
                  "using the slower torch forward. Install a C++ compiler (g++) and ninja to get it.",
                  RuntimeWarning, stacklevel=2)
    return None


class _FrozenHashGrid(torch.autograd.Function):
    @staticmethod
    def forward(ctx, positions: Tensor, table: Tensor, scalings: Tensor, offsets: Tensor, size: int,
                jacobian: bool) -> Tensor:
        with torch.profiler.record_function("nerfinv::hash_grid_forward"):  # named in profiles, else unseen
            features, jac = extension().forward(positions, table, scalings, offsets, size, jacobian)
        ctx.save_for_backward(jac)
        return features

    @staticmethod
    def backward(ctx, grad: Tensor):
        (jacobian,) = ctx.saved_tensors
        with torch.profiler.record_function("nerfinv::hash_grid_backward"):
            grad_positions = extension().backward(grad.contiguous(), jacobian)
        return grad_positions, None, None, None, None, None


def kernel_hash_forward(self: HashEncoding, in_tensor: Tensor) -> Tensor:
    """Drop-in for ``HashEncoding.pytorch_fwd``: the compiled kernel where it applies, else the fused
    torch forward."""
    if (self.hash_table.requires_grad or in_tensor.dtype != torch.float32 or in_tensor.device.type != "cpu"
            or extension() is None):
        return fused_hash_forward(self, in_tensor)
    flat = in_tensor.reshape(-1, 3).contiguous()
    # The Jacobian only where a graph is being recorded: nerfacto marks its sample positions as requiring a
    # gradient also when it evaluates the proposal networks under no_grad, which the kernel cannot see.
    jacobian = torch.is_grad_enabled() and flat.requires_grad
    out = _FrozenHashGrid.apply(flat, self.hash_table.detach(), self.scalings.to(torch.float32).contiguous(),
                                self.hash_offset.to(torch.int64), int(self.hash_table_size), jacobian)
    return out.view(*in_tensor.shape[:-1], out.shape[-1])


def use_hash_kernel(module: torch.nn.Module) -> int:
    """Switch every torch-backed ``HashEncoding`` inside ``module`` to :func:`kernel_hash_forward`.
    Returns how many were switched."""
    return use_fused_hash_encoding(module, kernel_hash_forward)


DensityFn = Callable[..., Tensor]


def _kernel_mlp(network: HashMLPDensityField) -> MLP | None:
    """The proposal network's MLP when the kernel computes what it computes: nerfstudio's torch MLP after a
    torch hash encoding, ReLU between its layers, nothing after the last, no skip connections, the infinity-norm
    scene contraction in front; else ``None``."""
    if network.use_linear or not isinstance(network.spatial_distortion, SceneContraction):
        return None
    if not math.isinf(float(network.spatial_distortion.order or 2)):
        return None
    encoding, mlp = network.mlp_base
    if not isinstance(encoding, HashEncoding) or encoding.tcnn_encoding is not None or not isinstance(mlp, MLP):
        return None
    if mlp.tcnn_encoding is not None or mlp._skip_connections or mlp.out_activation is not None:
        return None
    if not isinstance(mlp.activation, torch.nn.ReLU) or any(layer.bias is None for layer in mlp.layers):
        return None
    return mlp


def kernel_density_fn(network: HashMLPDensityField) -> DensityFn:
    """``network.density_fn`` computed by the kernel's ``density`` (one pass per sample through the contraction,
    hash grid, MLP and activation) where it applies: float32 CPU positions, no graph being recorded, weights
    that do not require gradients (nerfacto evaluates its proposal networks under ``no_grad`` once trained).
    Anywhere else, and for a network the kernel does not cover, nerfstudio's own."""
    mlp = _kernel_mlp(network)
    if mlp is None:
        return network.density_fn
    encoding = network.mlp_base[0]

    def density_fn(positions: Tensor, times: Tensor | None = None) -> Tensor:
        if (times is not None or positions.dtype != torch.float32 or positions.device.type != "cpu"
                or torch.is_grad_enabled() or extension() is None
                or any(parameter.requires_grad for parameter in network.parameters())):
            return network.density_fn(positions, times)
        unit = getattr(network.spatial_distortion, "unit", None)  # nerfacto-tiny's contraction unit
        with torch.profiler.record_function("nerfinv::density"):
            density = extension().density(
                positions.reshape(-1, 3).contiguous(), 1.0 if unit is None else float(unit),
                encoding.hash_table.contiguous(), encoding.scalings.to(torch.float32).contiguous(),
                encoding.hash_offset.to(torch.int64), int(encoding.hash_table_size),
                [layer.weight.contiguous() for layer in mlp.layers], [layer.bias.contiguous() for layer in mlp.layers],
                float(network.average_init_density))
        return density.view(*positions.shape[:-1], 1)

    return density_fn


def use_density_kernel(model: torch.nn.Module) -> int:
    """Point a nerfacto-like model's proposal density functions (``model.density_fns``, the bound
    ``density_fn`` of each proposal network, which its proposal sampler calls) at :func:`kernel_density_fn` of
    the same network; returns how many were covered."""
    fns = getattr(model, "density_fns", None)
    count = 0
    for i, fn in enumerate(fns if isinstance(fns, list) else []):
        network = getattr(fn, "__self__", None)
        if isinstance(network, HashMLPDensityField) and (fast := kernel_density_fn(network)) != fn:
            fns[i] = fast
            count += 1
    return count
