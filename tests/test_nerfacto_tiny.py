"""nerfacto-tiny: trains offline without worker processes, reaches a PSNR floor, and its faster hash
forward computes nerfstudio's function."""

import multiprocessing.process
import socket

import numpy as np
import pytest
import torch
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.field_components.encodings import HashEncoding
from torchmetrics.image import lpip

from nerfinv_plugin.model.evaluate import evaluate_split, psnr
from nerfinv_plugin.model.fused_hash import fused_hash_forward
from nerfinv_plugin.model.loading import load_model, read_config
from nerfinv_plugin.model.nerfacto_tiny import (
    LPIPSUnavailable,
    NerfactoTinyModel,
    NerfactoTinyModelConfig,
    lpips_disabled,
)
from nerfinv_plugin.model.opacity import EMPTY, OBJECT, UNKNOWN, opacity_label_stack, opacity_labels
from nerfinv_plugin.model.training import train_nerfacto_tiny
from nerfinv_plugin.synth.datasets import TrainingSetSpec, write_training_set

PSNR_FLOOR_DB = 24.0


@pytest.mark.parametrize("levels,log2_size,max_res", [(8, 15, 256), (5, 14, 128), (16, 19, 2048)])
def test_fused_hash_forward_matches_nerfstudio(levels, log2_size, max_res):
    torch.manual_seed(0)
    enc = HashEncoding(num_levels=levels, min_res=16, max_res=max_res, log2_hashmap_size=log2_size,
                       implementation="torch")
    x = torch.rand(2000, 3, requires_grad=True)
    x.data[:10] = torch.tensor([0.0, 0.5, 1.0])  # lattice points, where floor == ceil
    reference, ours = enc.pytorch_fwd(x), fused_hash_forward(enc, x)
    torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-7)
    cotangent = torch.randn_like(reference)
    grads_ref = torch.autograd.grad((reference * cotangent).sum(), [x, enc.hash_table])
    grads_ours = torch.autograd.grad((ours * cotangent).sum(), [x, enc.hash_table])
    for ref, got in zip(grads_ref, grads_ours):
        torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-5)


def test_lpips_stand_in_is_restored_after_the_context():
    original = lpip.LearnedPerceptualImagePatchSimilarity
    with pytest.raises(RuntimeError), lpips_disabled():
        assert isinstance(lpip.LearnedPerceptualImagePatchSimilarity(normalize=True), LPIPSUnavailable)
        raise RuntimeError("leave the context by an exception")
    assert lpip.LearnedPerceptualImagePatchSimilarity is original


def test_training_runs_with_network_unavailable_and_no_worker_processes(tmp_path, monkeypatch):
    spec = TrainingSetSpec(train_views=4, val_views=1, test_views=1, width=40, height=25)
    write_training_set(tmp_path / "data", "toy", spec, seed=0, spp=4, step=lambda: None)

    def no_network(*args, **kwargs):
        raise OSError("network disabled by the test")

    def no_processes(self):
        raise AssertionError(f"training started a process: {self}")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket.socket, "connect_ex", no_network)
    monkeypatch.setattr(socket, "getaddrinfo", no_network)
    monkeypatch.setattr(multiprocessing.process.BaseProcess, "start", no_processes)
    with pytest.raises(OSError):  # the guard is live: a download attempt would fail
        socket.create_connection(("pypi.org", 443), timeout=1)
    config = train_nerfacto_tiny(tmp_path / "data", tmp_path / "out", "offline", iterations=10,
                                 rays_per_batch=256)
    assert [p.name for p in (config.parent / "nerfstudio_models").glob("*.ckpt")] == ["step-000000009.ckpt"]
    loaded = load_model(config, device="cpu")
    assert isinstance(loaded.model.lpips, LPIPSUnavailable)


def test_tiny_model_reaches_psnr_floor_on_held_out_views(toy_run):
    config, data = toy_run
    loaded = load_model(config, device="cpu")
    scores = evaluate_split(loaded, data, "test")
    mean = float(np.mean([s.psnr for s in scores]))
    # An empty model (black everywhere) scores well on mostly black images: the model must beat it.
    black = float(np.mean([psnr(np.zeros_like(s.observed), s.observed) for s in scores]))
    assert mean >= PSNR_FLOOR_DB, f"held-out PSNR {mean:.2f} dB < {PSNR_FLOOR_DB} dB"
    assert mean >= black + 6.0, f"held-out PSNR {mean:.2f} dB barely beats an empty render ({black:.2f} dB)"


def _tiny_model(seed: int = 0) -> NerfactoTinyModel:
    torch.manual_seed(seed)
    config = NerfactoTinyModelConfig()
    return config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])),
                        num_train_data=4).eval()


def test_densities_follow_the_scene_scale_and_old_checkpoints_keep_theirs():
    """The same weights fitted to the same cameras at two scales (metres, and nerfstudio-data's unit cube)
    give the same optical depth along corresponding rays: density times length does not depend on the scale.
    A state dict from before densities followed the unit (no ``density_unit``) loads with its densities per
    model unit, as it was trained."""
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(20, 3))
    centres = 5.0 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    scale = 0.188
    metric, cube = _tiny_model(), _tiny_model()
    cube.load_state_dict(metric.state_dict())
    fit_metric = metric.fit_to_cameras(centres, 0.2)
    fit_cube = cube.fit_to_cameras(centres * scale, 0.2)
    assert fit_cube.unit == pytest.approx(scale * fit_metric.unit)
    points = torch.as_tensor(rng.uniform(-0.5, 0.5, (256, 3)), dtype=torch.float32)
    with torch.no_grad():
        metric_density = metric.field.density_fn(points)
        cube_density = cube.field.density_fn(points * scale)
        proposal_metric = metric.proposal_networks[0].density_fn(points)
        proposal_cube = cube.proposal_networks[0].density_fn(points * scale)
    assert metric_density.abs().max() > 0
    torch.testing.assert_close(cube_density * scale, metric_density, rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(proposal_cube * scale, proposal_metric, rtol=1e-4, atol=1e-7)

    reloaded = _tiny_model(seed=1)
    reloaded.load_state_dict(cube.state_dict())  # a checkpoint trained with densities per unit
    with torch.no_grad():
        torch.testing.assert_close(reloaded.field.density_fn(points * scale), cube_density)
    old = {k: v for k, v in cube.state_dict().items() if not k.endswith("density_unit")}
    before = _tiny_model(seed=2)
    before.load_state_dict(old)
    assert all(f.average_init_density == pytest.approx(0.01) for f in (before.field, *before.proposal_networks))


def test_opacity_labels_are_the_found_object_less_its_outline_and_what_lies_well_away_from_it():
    image = np.zeros((40, 60, 3))
    image[10:22, 20:40] = (0.1, 0.6, 0.3)  # a lit box over black space
    expected = np.full((40, 60), EMPTY, np.int8)
    expected[8:24, 18:42] = UNKNOWN  # within two pixels of the box
    expected[11:21, 21:39] = OBJECT  # inside it, off its outline
    np.testing.assert_array_equal(opacity_labels(image), expected)
    assert (opacity_labels(np.zeros((40, 60, 3))) == UNKNOWN).all()  # nothing found: nothing is asked
    stack = opacity_label_stack([image, np.zeros((30, 70, 3))])
    assert stack.shape == (2, 40, 70) and stack.dtype == torch.int8
    np.testing.assert_array_equal(stack[0, :, :60].numpy(), expected)
    assert (stack[0, :, 60:] == UNKNOWN).all()


def test_the_opacity_loss_asks_for_accumulation_one_on_the_object_and_zero_away_from_it_in_rgb_images_only():
    from nerfstudio.cameras.cameras import Cameras

    model = _tiny_model().train()
    model.fit_to_cameras(np.array([[0.0, 0.0, 5.0]]), 0.3)
    c2w = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5]]])
    camera = Cameras(camera_to_worlds=c2w, fx=60.0, fy=60.0, cx=16.0, cy=12.0, width=32, height=24)
    rng = np.random.default_rng(0)
    rows, cols = torch.as_tensor(rng.integers(0, 24, 64)), torch.as_tensor(rng.integers(0, 32, 64))
    bundle = camera.generate_rays(camera_indices=0, coords=torch.stack([rows, cols], -1).float() + 0.5)
    bundle.camera_indices = torch.zeros((64, 1), dtype=torch.long)
    outputs = model(bundle)
    labels = torch.full((2, 24, 32), UNKNOWN, dtype=torch.int8)
    labels[1, :, :10] = EMPTY
    labels[1, 6:18, 14:24] = OBJECT
    batch = {"image": torch.rand(64, 3), "indices": torch.stack([torch.ones(64, dtype=torch.long), rows, cols], -1)}
    model.opacity_labels = labels
    metrics = model.get_metrics_dict(outputs, batch)
    loss = model.get_loss_dict(outputs, batch, metrics)["object_opacity_loss"]
    ray_labels = labels[1, rows, cols]
    assert all(0 < int((ray_labels == label).sum()) < 64 for label in (OBJECT, EMPTY, UNKNOWN))
    accumulation = outputs["accumulation"].squeeze(-1)
    expected = model.config.object_opacity_loss_mult * torch.where(
        ray_labels == OBJECT, (1.0 - accumulation) ** 2, torch.where(ray_labels == EMPTY, accumulation**2, 0.0)).mean()
    torch.testing.assert_close(loss, expected)
    loss.backward()  # it trains the field
    assert any(p.grad is not None and p.grad.abs().max() > 0 for p in model.field.parameters())
    model.opacity_labels = None  # RGBA images: the random background teaches opacity
    assert "object_opacity_loss" not in model.get_loss_dict(outputs, dict(batch, image=torch.rand(64, 4)), metrics)
    model.opacity_labels = labels
    model.eval()  # nerfstudio's evaluation batches index the evaluation images
    assert "object_opacity_loss" not in model.get_loss_dict(outputs, batch, metrics)


@pytest.mark.parametrize("test_mode,background,labelled", [("val", "random", True), ("test", "random", False),
                                                           ("val", "white", False)])
def test_the_pipeline_labels_rgb_training_images_only_when_training_over_a_dark_background(
        toy_rgb_run, test_mode, background, labelled):
    config = read_config(toy_rgb_run[0]).pipeline  # nerfstudio-data on RGB images, as users train
    config.model.background_color = background
    pipeline = config.setup(device="cpu", test_mode=test_mode)  # ns-train's "val"; ns-eval / ns-viewer load "test"
    labels = pipeline.model.opacity_labels
    if not labelled:
        assert labels is None
        return
    dataset = pipeline.datamanager.train_dataset
    assert labels.shape[0] == len(dataset)
    for index in (0, 1, len(dataset) - 1):  # the first image is read apart from the others: neither lost nor repeated
        image = dataset.get_image_float32(index).numpy()
        height, width = image.shape[:2]
        np.testing.assert_array_equal(labels[index, :height, :width].numpy(), opacity_labels(image))
    assert 0 < float((labels == OBJECT).float().mean()) < 0.5


def test_the_pipeline_leaves_rgba_training_images_to_the_random_background(toy_run):
    config = read_config(toy_run[0]).pipeline  # the Blender dataparser, alpha kept
    pipeline = config.setup(device="cpu", test_mode="val")
    assert pipeline.datamanager.train_dataset.get_image_float32(0).shape[-1] == 4
    assert pipeline.model.opacity_labels is None
