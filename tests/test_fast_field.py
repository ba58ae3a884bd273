"""The faster field pieces used at inversion time compute nerfstudio's functions: the compiled hash-grid
kernel (values and gradients with respect to the positions; used only where the table is frozen) and the
max-norm scene contraction."""

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.spatial_distortions import SceneContraction

from nerfinv_plugin.model import hash_kernel
from nerfinv_plugin.model.contraction import use_max_norm_contraction
from nerfinv_plugin.model.hash_kernel import kernel_hash_forward, use_hash_kernel

needs_kernel = pytest.mark.skipif(not hash_kernel.enabled(), reason="NERFINV_HASH_KERNEL=0")


def frozen_encoding(levels: int, log2_size: int, max_res: int) -> HashEncoding:
    torch.manual_seed(0)
    enc = HashEncoding(num_levels=levels, min_res=16, max_res=max_res, log2_hashmap_size=log2_size,
                       implementation="torch")
    enc.hash_table.requires_grad_(False)
    return enc


@needs_kernel
@pytest.mark.parametrize("levels,log2_size,max_res", [(5, 14, 128), (16, 19, 2048)])
def test_kernel_matches_nerfstudio_values_and_position_gradients(levels, log2_size, max_res):
    assert hash_kernel.extension() is not None, "the kernel did not build on this machine"
    enc = frozen_encoding(levels, log2_size, max_res)
    x = torch.rand(3000, 3)
    x[:10] = torch.tensor([0.0, 0.5, 1.0])  # lattice points, where floor == ceil
    x = x.view(30, 100, 3).requires_grad_(True)  # batch dimensions are kept
    reference, ours = enc.pytorch_fwd(x), kernel_hash_forward(enc, x)
    assert ours.shape == reference.shape
    torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-7)
    cotangent = torch.randn_like(reference)
    (grad_ref,) = torch.autograd.grad((reference * cotangent).sum(), [x])
    (grad_ours,) = torch.autograd.grad((ours * cotangent).sum(), [x])
    torch.testing.assert_close(grad_ours, grad_ref, rtol=1e-4, atol=1e-4)


def test_trainable_tables_keep_the_torch_path():
    enc = frozen_encoding(4, 12, 64)
    enc.hash_table.requires_grad_(True)
    assert use_hash_kernel(torch.nn.ModuleList([enc])) == 1
    x = torch.rand(100, 3)
    out = enc(x)
    (grad_table,) = torch.autograd.grad(out.sum(), [enc.hash_table])
    assert grad_table.abs().sum() > 0  # the kernel gives tables no gradient; training needs one


@pytest.mark.parametrize("order", [float("inf"), None])
def test_max_norm_contraction_matches_nerfstudio(order):
    torch.manual_seed(0)
    x = (torch.randn(4000, 3) * 1.5).requires_grad_(True)  # about half inside the unit box
    reference, ours = SceneContraction(order=order), SceneContraction(order=order)
    assert use_max_norm_contraction(torch.nn.ModuleList([ours])) == 1
    expected, got = reference(x), ours(x)
    torch.testing.assert_close(got, expected)
    cotangent = torch.randn_like(expected)
    (grad_ref,) = torch.autograd.grad((expected * cotangent).sum(), [x])
    (grad_ours,) = torch.autograd.grad((got * cotangent).sum(), [x])
    torch.testing.assert_close(grad_ours, grad_ref)
