"""Loading runs from config.yml: moved folders, other nerfstudio models, clear errors for bad input."""

import shutil
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from nerfstudio.configs.base_config import MachineConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.instant_ngp import InstantNGPModelConfig
from nerfstudio.models.mipnerf import MipNerfModel
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.models.splatfacto import SplatfactoModelConfig
from nerfstudio.models.vanilla_nerf import VanillaModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from torchmetrics.functional.image.lpips import _NoTrainLpips

from nerfinv_plugin.initialization.bank import BankConfig, bank_intrinsics, cached_bank
from nerfinv_plugin.model.loading import ModelLoadError, load_model
from nerfinv_plugin.model.nerfacto_tiny import lpips_disabled
from nerfinv_plugin.model.render import AS_TRAINED, Intrinsics, render
from nerfinv_plugin.synth.datasets import TrainingSetSpec, write_training_set


@pytest.fixture(scope="module")
def small_data(tmp_path_factory) -> Path:
    data = tmp_path_factory.mktemp("small") / "data"
    spec = TrainingSetSpec(train_views=3, val_views=1, test_views=1, width=32, height=20)
    write_training_set(data, "toy", spec, seed=0, spp=4, step=lambda: None)
    return data


def _train(model_config, method_name: str, data: Path, out: Path, iterations: int = 2) -> Path:
    """Train a stock nerfstudio model for a few CPU iterations (LPIPS disabled only while training, as if
    it had been trained on a machine with network) and return its config.yml."""
    config = TrainerConfig(
        method_name=method_name, experiment_name="e", timestamp="t", output_dir=out,
        max_num_iterations=iterations, steps_per_save=iterations, mixed_precision=False, vis="tensorboard",
        steps_per_eval_batch=10**6, steps_per_eval_image=10**6, steps_per_eval_all_images=10**6,
        machine=MachineConfig(device_type="cpu"),
        optimizers={group: {"optimizer": AdamOptimizerConfig(lr=1e-3), "scheduler": None}
                    for group in ("proposal_networks", "fields")},
        pipeline=VanillaPipelineConfig(
            datamanager=VanillaDataManagerConfig(dataparser=BlenderDataParserConfig(), data=data,
                                                 train_num_rays_per_batch=64, eval_num_rays_per_batch=64),
            model=model_config),
    )
    config.logging.local_writer.enable = False
    config.save_config()
    with lpips_disabled():
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        trainer.train()
    return config.get_base_dir() / "config.yml"


def _no_network(monkeypatch) -> None:
    def refuse(*args, **kwargs):
        raise OSError("network disabled by the test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)


def _probe(loaded) -> torch.Tensor:
    c2w = torch.eye(4)[None, :3].clone()
    c2w[0, 2, 3] = 4.0
    c2w.requires_grad_(True)
    pixels = torch.tensor([[5, 5], [10, 16], [15, 20]])
    rgb = render(loaded, c2w, Intrinsics(30.0, 30.0, 16.0, 10.0, 32, 20), pixels).rgb
    rgb.sum().backward()
    return c2w.grad


def _assert_reaches_pose(grad: torch.Tensor) -> None:
    """A pose gradient that is there: finite everywhere, and not zero in the rotation nor the translation
    (a model that renders the same colour everywhere would give zero)."""
    assert torch.isfinite(grad).all(), grad
    assert float(grad[0, :, :3].abs().max()) > 0 and float(grad[0, :, 3].abs().max()) > 0, grad


def test_stock_nerfacto_with_lpips_weights_loads_offline(small_data, tmp_path, monkeypatch):
    model = NerfactoModelConfig(implementation="torch", num_levels=4, max_res=64, log2_hashmap_size=12,
                                hidden_dim=16, hidden_dim_color=16, num_proposal_samples_per_ray=(16, 8),
                                num_nerf_samples_per_ray=8, near_plane=1.0, far_plane=12.0)
    config = _train(model, "nerfacto", small_data, tmp_path)
    # A run trained with network access carries LPIPS weights in its checkpoint; add them as it would.
    checkpoint = next((config.parent / "nerfstudio_models").glob("*.ckpt"))
    state = torch.load(checkpoint, weights_only=False)
    lpips_state = _NoTrainLpips(net="alex", pnet_rand=True).state_dict()
    state["pipeline"].update({f"_model.lpips.net.{k}": v for k, v in lpips_state.items()})
    torch.save(state, checkpoint)
    _no_network(monkeypatch)
    loaded = load_model(config, device="cpu")
    assert type(loaded.model).__name__ == "NerfactoModel"
    assert all(not p.requires_grad for p in loaded.model.parameters())
    _assert_reaches_pose(_probe(loaded))


@pytest.mark.parametrize("name", ["vanilla-nerf", "mipnerf"])
def test_pure_torch_nerfs_render_with_pose_gradients_and_a_view_bank_on_cpu(name, small_data, tmp_path, monkeypatch):
    """Pose gradients, and the view bank that starts a run from nothing, on a briefly trained checkpoint
    (these models render about 100 rays/s on a CPU, so the bank is 12 views of 8 x 8 pixels): each view is
    the model's own render at that pose, the accumulation the fine level's (not the colour's fallback),
    and a second call reads the cache."""
    model = VanillaModelConfig(num_coarse_samples=8, num_importance_samples=8)
    if name == "mipnerf":
        model = replace(model, _target=MipNerfModel, loss_coefficients={"rgb_loss_coarse": 0.1, "rgb_loss_fine": 1.0})
    loaded = load_model(_train(model, name, small_data, tmp_path, iterations=1), device="cpu")
    _assert_reaches_pose(_probe(loaded))

    monkeypatch.setenv("NERFINV_CACHE", str(tmp_path / "cache"))
    config = BankConfig(subdivisions=0, in_plane=4, render_px=8, crop_px=8)
    bank, path, built = cached_bank(loaded, AS_TRAINED, np.zeros(3), 1.0, config)
    assert built and path.is_file() and bank.rgb.shape == (12, 8, 8, 3) and bank.accumulation.shape == (12, 8, 8)
    pixels = torch.stack(torch.meshgrid(torch.arange(8), torch.arange(8), indexing="ij"), -1).reshape(-1, 2)
    with torch.no_grad():
        out = render(loaded, torch.as_tensor(bank.c2w[5:6], dtype=torch.float32), bank_intrinsics(config), pixels)
    assert out.accumulation is not None
    expected_rgb = (out.rgb.clamp(0, 1) * 255).reshape(8, 8, 3).numpy()
    expected_acc = (out.accumulation.clamp(0, 1) * 255).reshape(8, 8).numpy()
    assert np.abs(bank.rgb[5] - expected_rgb).max() <= 1.0 and np.abs(bank.accumulation[5] - expected_acc).max() <= 1.0
    assert not np.array_equal(bank.accumulation, bank.rgb.max(-1))
    again, _, rebuilt = cached_bank(loaded, AS_TRAINED, np.zeros(3), 1.0, config)
    assert not rebuilt and np.array_equal(again.rgb, bank.rgb)


def _untrained_run(model_config, method_name: str, out: Path) -> Path:
    """A run folder for a model that cannot train on a CPU: real config.yml, checkpoint of its initial
    weights, identity dataparser transform."""
    config = TrainerConfig(method_name=method_name, experiment_name="e", timestamp="t", output_dir=out,
                           pipeline=VanillaPipelineConfig(model=model_config))
    config.save_config()
    with lpips_disabled():
        model = model_config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.5] * 3, [1.5] * 3])),
                                   num_train_data=1, metadata={}, device="cpu", grad_scaler=None)
    base = config.get_base_dir()
    (base / "nerfstudio_models").mkdir()
    torch.save({"step": 0, "pipeline": {f"_model.{k}": v for k, v in model.state_dict().items()}},
               base / "nerfstudio_models" / "step-000000000.ckpt")
    (base / "dataparser_transforms.json").write_text('{"transform": [[1,0,0,0],[0,1,0,0],[0,0,1,0]], "scale": 1.0}')
    return base / "config.yml"


@pytest.mark.skipif(torch.cuda.is_available(), reason="on CUDA these models render; the error is for CPUs")
@pytest.mark.parametrize("name,model_config,class_name", [
    ("instant-ngp", InstantNGPModelConfig(), "NGPModel"),
    ("splatfacto", SplatfactoModelConfig(num_random=500), "SplatfactoModel"),
])
def test_cuda_only_models_fail_with_one_line_naming_model_and_device(name, model_config, class_name, tmp_path):
    config = _untrained_run(model_config, name, tmp_path)
    with pytest.raises(ModelLoadError) as err:
        load_model(config, device="cpu")
    message = str(err.value)
    assert "\n" not in message and class_name in message and name in message and "cpu" in message


def test_moved_run_folder_loads_and_renders_the_same(toy_run, tmp_path):
    config, _ = toy_run
    original = load_model(config, device="cpu")
    moved = tmp_path / "elsewhere" / "run"
    shutil.copytree(config.parent, moved)
    loaded = load_model(moved / "config.yml", device="cpu")
    assert loaded.checkpoint.parent == moved / "nerfstudio_models"
    c2w = torch.eye(4)[None, :3].clone()
    c2w[0, 2, 3] = 4.0
    pixels = torch.tensor([[20, 30], [25, 40]])
    intrinsics = Intrinsics(60.0, 60.0, 40.0, 25.0, 80, 50)
    expected = render(original, c2w, intrinsics, pixels).rgb
    torch.testing.assert_close(render(loaded, c2w, intrinsics, pixels).rgb, expected)


def test_checkpoint_choice_latest_or_given_step(toy_run, tmp_path):
    config, _ = toy_run
    run = tmp_path / "run"
    shutil.copytree(config.parent, run)
    latest = next((run / "nerfstudio_models").glob("*.ckpt"))
    shutil.copy(latest, run / "nerfstudio_models" / "step-000000001.ckpt")
    assert load_model(run / "config.yml", device="cpu").checkpoint == latest
    assert load_model(run / "config.yml", step=1, device="cpu").checkpoint.name == "step-000000001.ckpt"
    with pytest.raises(ModelLoadError, match="no checkpoint step-000000007.ckpt"):
        load_model(run / "config.yml", step=7, device="cpu")


def test_clear_errors_for_bad_runs(toy_run, tmp_path):
    config, _ = toy_run
    with pytest.raises(ModelLoadError, match="no config file at .*config.yml"):
        load_model(tmp_path / "missing" / "config.yml")
    not_config = tmp_path / "other.yml"
    not_config.write_text(yaml.dump({"learning_rate": 0.01}))
    with pytest.raises(ModelLoadError, match="is not a nerfstudio config.yml"):
        load_model(not_config)
    garbage = tmp_path / "garbage.yml"
    garbage.write_bytes(b"\x00\xff{{: not yaml [")
    with pytest.raises(ModelLoadError, match="not a readable nerfstudio config"):
        load_model(garbage)
    run = tmp_path / "run"
    shutil.copytree(config.parent, run)
    shutil.rmtree(run / "nerfstudio_models")
    with pytest.raises(ModelLoadError, match="no checkpoint step-\\*.ckpt in .*nerfstudio_models"):
        load_model(run / "config.yml")


def test_cuda_asked_for_where_torch_sees_none_is_a_clear_error(toy_run, monkeypatch):
    """Checked on every machine: a CUDA machine is made to look like one without."""
    config, _ = toy_run
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ModelLoadError, match="--device cuda was asked for but torch sees no CUDA device"):
        load_model(config, device="cuda")
    assert load_model(config, device="auto").device == torch.device("cpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_a_run_loads_on_cuda_and_renders_as_on_the_cpu(toy_run):
    config, _ = toy_run
    on_cpu, on_cuda = load_model(config, device="cpu"), load_model(config, device="cuda")
    assert on_cuda.device.type == "cuda" and load_model(config, device="auto").device.type == "cuda"
    assert all(p.device.type == "cuda" and not p.requires_grad for p in on_cuda.model.parameters())
    c2w = torch.eye(4)[None, :3].clone()
    c2w[0, 2, 3] = 4.0
    pixels = torch.tensor([[20, 30], [25, 40], [10, 10]])
    intrinsics = Intrinsics(60.0, 60.0, 40.0, 25.0, 80, 50)
    expected = render(on_cpu, c2w, intrinsics, pixels).rgb
    got = render(on_cuda, c2w.cuda(), intrinsics, pixels).rgb
    assert got.device.type == "cuda"
    torch.testing.assert_close(got.cpu(), expected, rtol=1e-3, atol=1e-4)


def test_step_dependent_state_is_restored(toy_run, tmp_path):
    """nerfacto anneals its proposal weights over training; a loaded model must use the value of the
    checkpoint's step (here rewritten to 300, where the anneal is well below its final 1.0)."""
    config, _ = toy_run
    run = tmp_path / "run"
    shutil.copytree(config.parent, run)
    checkpoint = next((run / "nerfstudio_models").glob("*.ckpt"))
    state = torch.load(checkpoint, weights_only=False)
    state["step"] = 300
    torch.save(state, checkpoint)
    loaded = load_model(run / "config.yml", device="cpu")
    fraction = 300 / loaded.model.config.proposal_weights_anneal_max_num_iters
    slope = loaded.model.config.proposal_weights_anneal_slope
    expected = slope * fraction / ((slope - 1) * fraction + 1)
    assert expected < 0.9 and loaded.model.proposal_sampler._anneal == pytest.approx(expected)


def test_dataset_model_frame_conversions_match_nerfstudio():
    """Our dataset -> model mapping inverted by nerfstudio's own ``transform_poses_to_original_space``."""
    from nerfstudio.data.dataparsers.base_dataparser import transform_poses_to_original_space
    from scipy.spatial.transform import Rotation

    from nerfinv_plugin.model.loaded import LoadedModel

    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    transform[:3, 3] = [0.4, -1.2, 2.0]
    loaded = LoadedModel(None, None, Path("x"), 0, torch.device("cpu"), transform, 0.37)
    poses = np.stack([np.eye(4)] * 3)
    poses[:, :3, :3] = Rotation.random(3, random_state=0).as_matrix()
    poses[:, :3, 3] = np.random.default_rng(0).normal(size=(3, 3)) * 5
    model = loaded.dataset_to_model(poses)
    back = transform_poses_to_original_space(torch.as_tensor(model[:, :3]), torch.as_tensor(transform[:3]), 0.37,
                                             camera_convention="opengl").numpy()
    np.testing.assert_allclose(back, poses[:, :3], atol=1e-9)
    np.testing.assert_allclose(loaded.model_to_dataset(model), poses, atol=1e-9)
