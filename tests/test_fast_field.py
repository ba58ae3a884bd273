"""The faster field pieces used at inversion time compute nerfstudio's functions: the compiled hash-grid
kernel (values and gradients with respect to the positions; used only where the table is frozen), the fused
torch forward it falls back to (CUDA, trainable tables), the max-norm scene contraction, and the compiled
proposal density field (values; used only without gradients). Each runs on the CPU and, where there is one,
on CUDA."""

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.fields.density_fields import HashMLPDensityField

from nerfinv_plugin.model import hash_kernel
from nerfinv_plugin.model.contraction import use_max_norm_contraction
from nerfinv_plugin.model.hash_kernel import kernel_density_fn, kernel_hash_forward, use_density_kernel, use_hash_kernel
from nerfinv_plugin.model.nerfacto_tiny import ScaledContraction

needs_kernel = pytest.mark.skipif(not hash_kernel.enabled(), reason="NERFINV_HASH_KERNEL=0")
DEVICES = [pytest.param("cpu"), pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                              reason="no CUDA device"))]


def frozen_encoding(levels: int, log2_size: int, max_res: int, device: str = "cpu") -> HashEncoding:
    torch.manual_seed(0)
    enc = HashEncoding(num_levels=levels, min_res=16, max_res=max_res, log2_hashmap_size=log2_size,
                       implementation="torch").to(device)
    enc.hash_table.requires_grad_(False)
    return enc


@needs_kernel
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("levels,log2_size,max_res", [(5, 14, 128), (16, 19, 2048)])
def test_kernel_matches_nerfstudio_values_and_position_gradients(levels, log2_size, max_res, device):
    """On the CPU the compiled kernel; on CUDA the fused torch forward that ``kernel_hash_forward`` takes there."""
    if device == "cpu":
        assert hash_kernel.extension() is not None, "the kernel did not build on this machine"
    enc = frozen_encoding(levels, log2_size, max_res, device)
    x = torch.rand(3000, 3, device=device)
    x[:10] = torch.tensor([0.0, 0.5, 1.0], device=device)  # lattice points, where floor == ceil
    x = x.view(30, 100, 3).requires_grad_(True)  # batch dimensions are kept
    reference, ours = enc.pytorch_fwd(x), kernel_hash_forward(enc, x)
    assert ours.shape == reference.shape
    torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-7)
    cotangent = torch.randn_like(reference)
    (grad_ref,) = torch.autograd.grad((reference * cotangent).sum(), [x])
    (grad_ours,) = torch.autograd.grad((ours * cotangent).sum(), [x])
    torch.testing.assert_close(grad_ours, grad_ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("device", DEVICES)
def test_trainable_tables_keep_the_torch_path(device):
    """The kernel gives tables no gradient; training needs nerfstudio's, and gets it."""
    reference, enc = frozen_encoding(4, 12, 64, device), frozen_encoding(4, 12, 64, device)
    for table in (reference.hash_table, enc.hash_table):
        table.requires_grad_(True)
    assert use_hash_kernel(torch.nn.ModuleList([enc])) == 1
    x = torch.rand(100, 3, device=device)
    expected, out = reference(x), enc(x)
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-7)
    cotangent = torch.randn_like(out)
    (grad_ref,) = torch.autograd.grad((expected * cotangent).sum(), [reference.hash_table])
    (grad_table,) = torch.autograd.grad((out * cotangent).sum(), [enc.hash_table])
    torch.testing.assert_close(grad_table, grad_ref, rtol=1e-5, atol=1e-6)
    assert int((grad_table != 0).sum()) > 100  # the 100 points touch many table entries


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("order", [float("inf"), None])
def test_max_norm_contraction_matches_nerfstudio(order, device):
    torch.manual_seed(0)
    x = (torch.randn(4000, 3, device=device) * 1.5).requires_grad_(True)  # about half inside the unit box
    reference, ours = SceneContraction(order=order), SceneContraction(order=order)
    assert use_max_norm_contraction(torch.nn.ModuleList([ours])) == 1
    expected, got = reference(x), ours(x)
    torch.testing.assert_close(got, expected)
    cotangent = torch.randn_like(expected)
    (grad_ref,) = torch.autograd.grad((expected * cotangent).sum(), [x])
    (grad_ours,) = torch.autograd.grad((got * cotangent).sum(), [x])
    torch.testing.assert_close(grad_ours, grad_ref)


def proposal_network(unit: float | None, hidden: int, layers: int, device: str = "cpu") -> HashMLPDensityField:
    """A frozen proposal density field with weights that make densities of every size (not its zero init)."""
    torch.manual_seed(1)
    contraction = SceneContraction(order=float("inf")) if unit is None else ScaledContraction(unit)
    network = HashMLPDensityField(torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), num_layers=layers, hidden_dim=hidden,
                                  spatial_distortion=contraction, num_levels=5, max_res=128, log2_hashmap_size=14,
                                  average_init_density=0.01, implementation="torch")
    with torch.no_grad():
        network.encoding.hash_table.uniform_(-1.5, 1.5)
        for layer in network.mlp_base[1].layers:
            layer.weight.uniform_(-1.0, 1.0).mul_(4.0 / layer.in_features**0.5)
            layer.bias.uniform_(-1.0, 1.0)
    use_max_norm_contraction(network)
    use_hash_kernel(network)
    return network.to(device).requires_grad_(False)


@needs_kernel
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("unit,hidden,layers", [(0.17, 16, 2), (None, 64, 3)])
def test_density_kernel_matches_nerfstudios_proposal_network(unit, hidden, layers, device):
    """Positions inside the contraction's unit cube, outside it (contracted), and far out; on CUDA, or with a
    graph being recorded, nerfstudio's own function runs."""
    network = proposal_network(unit, hidden, layers, device)
    scale = 1.0 if unit is None else unit
    x = (torch.rand(40, 50, 3, device=device) - 0.5) * 3.0 * scale
    x[0] *= 100.0
    x = x.requires_grad_(True)  # as nerfacto's sample positions do, evaluated under no_grad all the same
    fn = kernel_density_fn(network)
    with torch.no_grad():
        expected, got = network.density_fn(x), fn(x)
    assert got.shape == expected.shape == (40, 50, 1)
    assert float(expected.max()) > 100 * float(expected.min()) > 0  # densities of every size were compared
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-9)
    with_graph = fn(x)  # nerfstudio's, differentiable
    assert with_graph.requires_grad
    torch.testing.assert_close(with_graph.detach(), expected)


def test_density_kernel_covers_nerfactos_proposal_networks_and_leaves_others():
    """``use_density_kernel`` swaps the bound density functions a nerfacto model hands its proposal sampler,
    including one network shared by both levels, and leaves a network with a linear head alone; a trainable
    network keeps nerfstudio's function (the thesis' loop trains nothing, but makes the weights trainable)."""
    shared, linear = proposal_network(0.2, 16, 2), proposal_network(0.2, 16, 2)
    linear.use_linear = True
    model = torch.nn.Module()
    model.density_fns = [shared.density_fn, shared.density_fn, linear.density_fn]
    assert use_density_kernel(model) == 2
    assert model.density_fns[2] == linear.density_fn and model.density_fns[0] != shared.density_fn
    x = torch.rand(500, 3) * 0.3
    shared.requires_grad_(True)
    with torch.no_grad():
        reference = shared.density_fn(x)
        torch.testing.assert_close(model.density_fns[0](x), reference, rtol=0, atol=0)  # nerfstudio's, bit for bit


def test_the_kernel_is_built_with_openmp_else_on_one_thread_else_not_at_all(monkeypatch):
    """A compiler without OpenMP still builds the kernel (one thread); with no working build a warning says
    so once and the torch forward is used. Each set of flags has its own cached build."""
    import torch.utils.cpp_extension as cpp_extension

    monkeypatch.setenv("NERFINV_HASH_KERNEL", "1")
    builds: list[tuple[str, list[str], list[str]]] = []

    def load(name, sources, extra_cflags, extra_ldflags, verbose):
        builds.append((name, extra_cflags, extra_ldflags))
        if "-fopenmp" in extra_cflags or fail_all:
            raise RuntimeError("c++: error: unsupported option '-fopenmp'")
        return "single-threaded kernel"

    monkeypatch.setattr(cpp_extension, "load", load)
    try:
        fail_all = False
        hash_kernel.extension.cache_clear()
        assert hash_kernel.extension() == "single-threaded kernel"
        assert [flags for _, flags, _ in builds] == [["-O3", "-fopenmp"], ["-O3"]]
        assert builds[0][2] == ["-fopenmp"] and builds[1][2] == [] and builds[0][0] != builds[1][0]
        fail_all = True
        hash_kernel.extension.cache_clear()
        with pytest.warns(RuntimeWarning, match="could not be built"):
            assert hash_kernel.extension() is None
    finally:
        hash_kernel.extension.cache_clear()
