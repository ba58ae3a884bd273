"""A faster pure-torch forward for nerfstudio's ``HashEncoding``, computing the same function.

nerfstudio's torch path gathers the 8 cell corners with 8 separate advanced-indexing calls and blends
them in 7 pairwise steps. On a CPU, the backward of advanced indexing (``index_put_`` with accumulation)
dominates a training step. Here the 8 corners are hashed in one batch, gathered with one
``index_select`` (whose backward is a single ``index_add_``) and blended with trilinear weights in one
product. Parameters, hash function and table layout are untouched, so checkpoints are interchangeable and
outputs agree with nerfstudio's to float rounding (tested).
"""

import contextlib
import types
from collections.abc import Callable, Iterator

import torch
from nerfstudio.field_components.encodings import HashEncoding
from torch import Tensor

# nerfstudio's primes, as 32-bit two's complement: the table size is a power of two below 2**31, and the
# low bits of products and xors do not depend on the high bits, so int32 arithmetic that wraps gives the
# same table index as nerfstudio's int64 arithmetic, at half the memory traffic.
_PRIMES = (1, 2654435761 - 2**32, 805459861)


def fused_hash_forward(self: HashEncoding, in_tensor: Tensor) -> Tensor:
    """Drop-in for ``HashEncoding.pytorch_fwd``: [..., 3] in [0, 1] -> [..., levels * features].

    Corners are laid out [z, y, x] with 0 = floor and 1 = ceil on each axis; the hash of a corner is the
    xor of one per-axis term, so the 8 hashes are an outer xor of three [.., 2] tensors.
    """
    scaled = in_tensor[..., None, :] * self.scalings.view(-1, 1).to(in_tensor)  # [..., L, 3]
    lower = torch.floor(scaled)
    frac = scaled - lower  # the only differentiable path to the input, as in nerfstudio
    ends = torch.stack([lower, torch.ceil(scaled)], -1).int()  # [..., L, 3, 2]
    hx, hy, hz = (ends[..., a, :] * prime for a, prime in enumerate(_PRIMES))  # each [..., L, 2]
    index = hz[..., :, None] ^ (hy[..., :, None] ^ hx[..., None, :]).flatten(-2)[..., None, :]  # [..., L, 2, 4]
    offsets = self.hash_offset.to(device=index.device, dtype=torch.int32)[:, None]
    index = (index & (self.hash_table_size - 1)).flatten(-2) + offsets  # [..., L, 8]
    w = torch.stack([1 - frac, frac], -1)  # [..., L, 3, 2]
    weights = (w[..., 2, :, None] * (w[..., 1, :, None] * w[..., 0, None, :]).flatten(-2)[..., None, :])
    # A long index: the backward of index_select then scatters far faster than with an int32 one.
    features = self.hash_table.index_select(0, index.reshape(-1).long()).view(*index.shape, -1)  # [.., L, 8, F]
    return (features * weights.flatten(-2)[..., None]).sum(-2).flatten(-2)  # [..., L * F]


def use_fused_hash_encoding(module: torch.nn.Module, forward: Callable[[HashEncoding, Tensor], Tensor] | None = None
                            ) -> int:
    """Switch every torch-backed ``HashEncoding`` inside ``module`` to ``forward`` (default
    :func:`fused_hash_forward`). Returns how many were switched (tcnn-backed encodings are left alone)."""
    count = 0
    for sub in module.modules():
        if isinstance(sub, HashEncoding) and sub.tcnn_encoding is None:
            sub.pytorch_fwd = types.MethodType(forward or fused_hash_forward, sub)
            count += 1
    return count


@contextlib.contextmanager
def stock_hash_encoding(module: torch.nn.Module) -> Iterator[None]:
    """Within the block, hash encodings inside ``module`` run nerfstudio's own torch forward again (for
    comparing against code that used stock nerfstudio); the fused forward returns on exit."""
    switched = [sub for sub in module.modules() if isinstance(sub, HashEncoding) and "pytorch_fwd" in vars(sub)]
    saved = [vars(sub).pop("pytorch_fwd") for sub in switched]
    try:
        yield
    finally:
        for sub, method in zip(switched, saved):
            sub.pytorch_fwd = method
