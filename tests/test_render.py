"""Differentiable batched rendering of a loaded model: gradients, batching, chunking, the no-grad patch."""

import json

import numpy as np
import pytest
import torch
from frozen_depths import frozen_sample_depths
from scipy.spatial.transform import Rotation

from nerfinv_plugin.data.images import read_rgb_over_black
from nerfinv_plugin.inversion.optimizer import candidate_losses
from nerfinv_plugin.model.evaluate import psnr
from nerfinv_plugin.model.gradients import keep_gradients
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.model.render import (
    Intrinsics,
    RenderSettings,
    bound_to_target,
    pinhole_cameras,
    ray_bundle,
    render,
    render_image,
    render_settings,
)

DEVICES = [pytest.param("cpu"), pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                              reason="no CUDA device"))]


@pytest.fixture(scope="module", params=DEVICES)
def toy(toy_run, request):
    """The fixture model loaded on each device (CUDA where there is one)."""
    config, data = toy_run
    return load_model(config, device=request.param), data


def _view(data, split: str, index: int) -> tuple[np.ndarray, Intrinsics, str]:
    meta = json.loads((data / f"transforms_{split}.json").read_text())
    frame = meta["frames"][index]
    width, height = 80, 50
    focal = 0.5 * width / np.tan(0.5 * meta["camera_angle_x"])
    return np.asarray(frame["transform_matrix"]), Intrinsics(focal, focal, width / 2, height / 2, width, height), \
        frame["file_path"]


def _object_pixels(loaded, c2w, intrinsics, count: int, seed: int = 0) -> torch.Tensor:
    """Pixels on the object (where the render is not background), so gradients are informative."""
    image = render_image(loaded, c2w, intrinsics)
    rows, cols = np.nonzero(image.max(-1) > 0.1)
    pick = np.random.default_rng(seed).choice(len(rows), size=min(count, len(rows)), replace=False)
    return torch.as_tensor(np.stack([rows[pick], cols[pick]], 1))


def _perturbed(c2w0: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """c2w = [R(w) | t] @ c2w0 with delta = [t, w]: a left (world-frame) update, written independently of
    the engine's SE(3) code."""
    w = delta[3:]
    theta = torch.sqrt((w * w).sum() + 1e-24)
    k = torch.zeros(3, 3, dtype=delta.dtype)
    k[0, 1], k[0, 2], k[1, 0], k[1, 2], k[2, 0], k[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    rot = torch.eye(3, dtype=delta.dtype) + torch.sin(theta) / theta * k + (1 - torch.cos(theta)) / theta**2 * k @ k
    top = torch.cat([rot, delta[:3, None]], 1)
    update = torch.cat([top, torch.tensor([[0.0, 0, 0, 1]], dtype=delta.dtype)], 0)
    return (update @ c2w0)[None]


def test_pose_gradient_matches_finite_differences(toy):
    loaded, data = toy
    c2w_data, intrinsics, _ = _view(data, "test", 0)
    c2w0 = torch.as_tensor(loaded.dataset_to_model(c2w_data), dtype=torch.float32)
    pixels = _object_pixels(loaded, c2w0.numpy(), intrinsics, 300)
    offset = torch.tensor([0.03, -0.02, 0.02, 0.02, -0.015, 0.01])  # about 1.5 degrees and 4 cm away
    with torch.no_grad():
        target = render(loaded, _perturbed(c2w0, offset), intrinsics, pixels).rgb

    def loss(delta: torch.Tensor) -> torch.Tensor:
        return ((render(loaded, _perturbed(c2w0, delta), intrinsics, pixels).rgb - target) ** 2).mean()

    with frozen_sample_depths(loaded.model):
        delta = torch.zeros(6, requires_grad=True)
        loss(delta).backward()
        grad = delta.grad.clone()
        assert grad.abs().max() > 0
        # Along the gradient and along every axis that carries at least a tenth of it.
        directions = [grad / grad.norm()] + [torch.eye(6)[i] for i in range(6)
                                             if grad[i].abs() > 0.1 * grad.abs().max()]
        h = 1e-3
        for d in directions:
            with torch.no_grad():
                numeric = float(loss(h * d) - loss(-h * d)) / (2 * h)
            analytic = float((grad * d).sum())
            assert abs(numeric - analytic) <= 0.05 * abs(analytic), (d, numeric, analytic)
    # With the sampling live (as in inversion), the slope along the gradient still agrees closely.
    with torch.no_grad():
        d = grad / grad.norm()
        live = float(loss(h * d) - loss(-h * d)) / (2 * h)
    assert abs(live - float(grad.norm())) <= 0.1 * float(grad.norm()), (live, float(grad.norm()))


def test_rendering_a_training_pose_reproduces_the_image(toy):
    loaded, data = toy
    c2w_data, intrinsics, file_path = _view(data, "train", 0)
    observed = read_rgb_over_black(data / (file_path[2:] + ".png"))
    rendered = render_image(loaded, loaded.dataset_to_model(c2w_data), intrinsics)
    black = psnr(np.zeros_like(observed), observed)
    assert psnr(rendered, observed) > max(24.0, black + 6.0)


def _candidates_about_test_view(toy, count: int, seed: int):
    """``(loaded, the test view's pose [4, 4], its intrinsics, count poses about it [count, 4, 4])``, model frame."""
    loaded, data = toy
    c2w_data, intrinsics, _ = _view(data, "test", 1)
    c2w0 = torch.as_tensor(loaded.dataset_to_model(c2w_data), dtype=torch.float32)
    rng = np.random.default_rng(seed)
    poses = torch.stack([_perturbed(c2w0, torch.as_tensor(rng.normal(0, 0.03, 6), dtype=torch.float32))[0]
                         for _ in range(count)])
    return loaded, c2w0, intrinsics, poses


def test_batch_of_candidates_equals_single_renders_and_chunking_changes_nothing(toy):
    loaded, c2w0, intrinsics, poses = _candidates_about_test_view(toy, 4, seed=0)
    pixels = _object_pixels(loaded, c2w0.numpy(), intrinsics, 120)
    poses.requires_grad_(True)
    batched = render(loaded, poses, intrinsics, pixels)
    (batched.rgb.square().sum() + batched.accumulation.sum()).backward()
    grad_batched = poses.grad.clone()
    poses.grad = None
    chunked = render(loaded, poses, intrinsics, pixels, RenderSettings(chunk_rays=37))  # chunks cut across candidates
    (chunked.rgb.square().sum() + chunked.accumulation.sum()).backward()
    torch.testing.assert_close(chunked.rgb, batched.rgb, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(chunked.accumulation, batched.accumulation, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(poses.grad, grad_batched, rtol=1e-4, atol=1e-6)
    for i in range(4):
        single = render(loaded, poses[i:i + 1].detach(), intrinsics, pixels)
        # float32 matrix products over a batch of another size may sum in another order (seen: 6e-6 on one of
        # 360 values with one torch thread); a mixed-up candidate would be off by about 0.1
        torch.testing.assert_close(single.rgb[0], batched.rgb[i].detach(), rtol=1e-5, atol=1e-5)
    assert batched.rgb.shape == (4, 120, 3) and batched.accumulation.shape == (4, 120, 1)


def test_candidate_losses_back_propagate_chunk_by_chunk(toy):
    """The optimizer's losses back-propagate one chunk at a time (memory bounded by a chunk): with chunks cut
    across candidates the losses and the pose gradients are those of one chunk. Every chunk's graph starts in
    the one ray bundle of all rays; before that was kept, a second chunk's backward raised (any run whose
    candidates x pixels exceeded the chunk, on CPU and CUDA alike)."""
    loaded, c2w0, intrinsics, poses = _candidates_about_test_view(toy, 3, seed=1)
    pixels = _object_pixels(loaded, c2w0.numpy(), intrinsics, 50)
    observed = render(loaded, c2w0[None], intrinsics, pixels).rgb[0].detach()  # the truth's colours
    results = []
    for chunk in (150, 40):
        leaf = poses.clone().requires_grad_(True)
        losses = candidate_losses(loaded, leaf, intrinsics, pixels, observed, "mse", True,
                                  RenderSettings(chunk_rays=chunk))
        results.append((losses, leaf.grad))
    (whole, grad_whole), (chunked, grad_chunked) = results
    torch.testing.assert_close(chunked, whole, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(grad_chunked, grad_whole, rtol=1e-4, atol=1e-6)
    assert grad_whole.abs().max() > 1e-4


def test_colour_and_accumulation_are_nerfstudios_own_outputs_and_gradients(toy):
    """Renders of nerfacto skip the depths its get_outputs also computes; colour, accumulation and the pose
    gradient through them are the numbers of nerfstudio's forward all the same."""
    loaded, data = toy
    c2w_data, intrinsics, _ = _view(data, "test", 2)
    c2w = torch.as_tensor(loaded.dataset_to_model(c2w_data), dtype=torch.float32)[None].requires_grad_(True)
    pixels = _object_pixels(loaded, c2w[0].detach().numpy(), intrinsics, 96)
    ours = render(loaded, c2w, intrinsics, pixels, RenderSettings(chunk_rays=10_000))
    (ours.rgb.square().sum() + ours.accumulation.sum()).backward()
    grad_ours, c2w.grad = c2w.grad.clone(), None
    outputs = loaded.model(ray_bundle(loaded, c2w, intrinsics, pixels))  # nerfstudio's Model.forward
    assert {"depth", "expected_depth", "prop_depth_0"} <= set(outputs)
    (outputs["rgb"].square().sum() + outputs["accumulation"].sum()).backward()
    torch.testing.assert_close(ours.rgb[0], outputs["rgb"].detach(), rtol=0, atol=0)
    torch.testing.assert_close(ours.accumulation[0], outputs["accumulation"].detach(), rtol=0, atol=0)
    torch.testing.assert_close(grad_ours, c2w.grad, rtol=1e-6, atol=1e-9)


def test_rays_and_outputs_follow_the_pose_convention(toy):
    """The ray of the principal point leaves the camera centre along -z of the pose (OpenGL axes)."""
    loaded, _ = toy
    rot = torch.as_tensor(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), dtype=torch.float32)
    c2w = torch.eye(4)[None].clone()
    c2w[0, :3, :3], c2w[0, :3, 3] = rot, torch.tensor([0.5, -1.0, 4.0])
    intrinsics = Intrinsics(60.0, 60.0, 40.0, 25.0, 80, 50)
    bundle = ray_bundle(loaded, c2w.to(loaded.device), intrinsics, torch.tensor([[24, 39], [0, 0]]))
    assert bundle.origins.device.type == loaded.device.type
    torch.testing.assert_close(bundle.origins[0].cpu(), c2w[0, :3, 3])
    # Pixel (row 24, col 39) is sampled at (39.5, 24.5): half a pixel left of and above (40, 25); image
    # up is +y in OpenGL camera axes, and the camera looks along -z.
    centre_dir = rot @ torch.tensor([-0.5 / 60, 0.5 / 60, -1.0])
    torch.testing.assert_close(bundle.directions[0].cpu(), centre_dir / centre_dir.norm(), rtol=1e-5, atol=1e-6)


def test_ray_bundle_is_nerfstudios_pinhole_camera_with_its_gradients(toy):
    """The bundle is what ``Cameras.generate_rays`` gives for the same poses and pixels (origins, unit
    directions, pixel areas, direction norms), and a loss on them back-propagates to the poses alike."""
    loaded, _ = toy
    rotations = Rotation.from_rotvec([[0.3, -0.2, 0.5], [-1.1, 0.4, 2.0], [0.0, 2.5, -0.3]]).as_matrix()
    c2w = torch.eye(4).repeat(3, 1, 1)
    c2w[:, :3, :3] = torch.as_tensor(rotations, dtype=torch.float32)
    c2w[:, :3, 3] = torch.tensor([[0.5, -1.0, 4.0], [2.0, 0.3, -1.5], [-0.2, -3.0, 0.7]])
    intrinsics = Intrinsics(61.0, 58.5, 41.3, 24.2, 80, 50)
    pixels = torch.tensor([[0, 0], [24, 39], [49, 79], [7, 61], [33, 2]])
    ours_c2w, theirs_c2w = (c2w.clone().to(loaded.device).requires_grad_(True) for _ in range(2))
    ours = ray_bundle(loaded, ours_c2w, intrinsics, pixels)
    cameras = pinhole_cameras(theirs_c2w[:, :3], intrinsics)
    theirs = cameras.generate_rays(camera_indices=torch.arange(3, device=loaded.device).repeat_interleave(5)[:, None],
                                   coords=(pixels.to(loaded.device, torch.float32) + 0.5).repeat(3, 1))
    for name in ("origins", "directions", "pixel_area"):
        torch.testing.assert_close(getattr(ours, name), getattr(theirs, name), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(ours.metadata["directions_norm"], theirs.metadata["directions_norm"])
    assert ours.camera_indices.shape == theirs.camera_indices.shape and not ours.camera_indices.any()
    weights = torch.linspace(-1.0, 2.0, 15 * 3, device=loaded.device).reshape(15, 3)

    def loss(bundle):
        return (((bundle.origins + 0.7 * bundle.directions) * weights).sum() + 3.0 * bundle.pixel_area.sum())

    loss(ours).backward()
    loss(theirs).backward()
    torch.testing.assert_close(ours_c2w.grad, theirs_c2w.grad, rtol=1e-5, atol=1e-6)
    assert float(ours_c2w.grad[:, :, :3].abs().max()) > 0.1  # the rotations get a gradient, not only the origins


def test_keep_gradients_patches_one_model_and_is_undone(toy):
    loaded, _ = toy
    model = loaded.model
    c2w = torch.eye(4, device=loaded.device)[None, :3].clone()
    c2w[0, 2, 3] = 4.0
    c2w.requires_grad_(True)
    intrinsics = Intrinsics(10.0, 10.0, 2.0, 2.0, 4, 4)
    pixels = torch.stack(torch.meshgrid(torch.arange(4), torch.arange(4), indexing="ij"), -1).reshape(-1, 2)

    def outputs():
        bundle = ray_bundle(loaded, c2w, intrinsics, pixels).reshape((4, 4))
        return model.get_outputs_for_camera_ray_bundle(bundle)["rgb"]

    assert not outputs().requires_grad  # nerfstudio's no_grad
    with keep_gradients(model):
        rgb = outputs()
        assert rgb.requires_grad
        rgb.sum().backward()
    # The patched method gives the colours and the pose gradient that our renderer gives on the same rays.
    patched = c2w.grad.clone()
    c2w.grad = None
    ours = render(loaded, c2w, intrinsics, pixels).rgb
    ours.sum().backward()
    torch.testing.assert_close(rgb.detach().reshape(-1, 3), ours.detach()[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(patched, c2w.grad, rtol=1e-4, atol=1e-6)
    assert float(patched.abs().max()) > 1e-4  # and the rays see the object: the gradient says something
    assert not outputs().requires_grad
    with pytest.raises(KeyError), keep_gradients(model):
        raise KeyError("leave by an exception")
    assert "get_outputs_for_camera_ray_bundle" not in vars(model) and not outputs().requires_grad


def test_rays_bounded_to_a_target_sphere_render_as_sharp_with_a_third_of_the_samples(toy, monkeypatch):
    loaded, data = toy
    c2w_data, intrinsics, file_path = _view(data, "train", 0)
    observed = read_rgb_over_black(data / (file_path[2:] + ".png"))
    c2w = loaded.dataset_to_model(c2w_data)
    full = psnr(render_image(loaded, c2w, intrinsics), observed)
    centre = torch.as_tensor(loaded.dataset_to_model(np.eye(4))[:3, 3], dtype=torch.float32)
    sampler = loaded.model.proposal_sampler
    trained = (sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray)
    rendered_rays = []
    forward = sampler.forward  # every render of a ray bundle samples it once, through whichever path

    def counting(bundle, **kwargs):
        rendered_rays.append(len(bundle))
        return forward(bundle, **kwargs)

    settings = render_settings(loaded, (centre, 1.0 * loaded.dataparser_scale), (16, 8), 12)
    monkeypatch.setattr(sampler, "forward", counting)
    bounded = render_image(loaded, c2w, intrinsics, settings)
    image_rays = sum(rendered_rays)
    rows, cols = np.meshgrid(np.arange(intrinsics.height), np.arange(intrinsics.width), indexing="ij")
    everywhere = torch.as_tensor(np.stack([rows.ravel(), cols.ravel()], 1))
    hits = bound_to_target(settings, ray_bundle(loaded, torch.as_tensor(c2w[None], dtype=torch.float32),
                                                intrinsics, everywhere)).reshape(rows.shape).numpy()
    # The camera looks at the sphere's centre from 5 m: the ray through the image centre crosses it
    # from 4 m to 6 m (model units follow the dataparser scale).
    middle = torch.tensor([[intrinsics.height // 2, intrinsics.width // 2]])
    bundle = ray_bundle(loaded, torch.as_tensor(c2w[None], dtype=torch.float32), intrinsics, middle)
    assert bool(bound_to_target(settings, bundle)[0])
    distance = float(np.linalg.norm(c2w[:3, 3] - centre.numpy()))
    assert float(bundle.nears[0]) == pytest.approx(distance - loaded.dataparser_scale, abs=0.02)
    assert float(bundle.fars[0]) == pytest.approx(distance + loaded.dataparser_scale, abs=0.02)
    # The gradients are compared 4 degrees off the truth (turned about the target), where the pose error
    # drives them: at the truth itself they are the model's noise, and a retrained fixture gave a cosine of
    # 0.77 there (0.99 with the one before).
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(4.0) * np.array([1.0, 1.0, 0.0]) / np.sqrt(2)).as_matrix()
    about = np.eye(4)
    about[:3, 3] = centre.numpy()
    off = about @ turn @ np.linalg.inv(about) @ c2w
    leaf = torch.as_tensor(off[None, :3], dtype=torch.float32).requires_grad_(True)
    pixels = _object_pixels(loaded, c2w, intrinsics, 64)
    target = torch.as_tensor(observed, dtype=torch.float32, device=loaded.device)[pixels[:, 0], pixels[:, 1]]
    (render(loaded, leaf, intrinsics, pixels, settings).rgb[0] - target).pow(2).mean().backward()
    bounded_grad = leaf.grad.clone()
    # The sample counts hold only while a render runs, also when it fails.
    assert (sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray) == trained
    monkeypatch.setattr(sampler, "forward", lambda bundle, **kwargs: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        render(loaded, leaf, intrinsics, pixels, settings)
    assert (sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray) == trained
    monkeypatch.setattr(sampler, "forward", forward)
    # Gradients reach the pose through the bounded rays, and point where the unbounded rays' do.
    leaf.grad = None
    (render(loaded, leaf, intrinsics, pixels).rgb[0] - target).pow(2).mean().backward()
    assert torch.isfinite(bounded_grad).all()
    cosine = float(torch.nn.functional.cosine_similarity(bounded_grad.flatten(), leaf.grad.flatten(), 0))
    assert cosine > 0.9
    assert 0 < hits.sum() < hits.size and image_rays == hits.sum()  # rays that miss the sphere: not rendered
    assert np.all(bounded[~hits] == 0.0)  # but black, as the model renders empty space
    assert psnr(bounded, observed) > full - 0.5, (psnr(bounded, observed), full)
