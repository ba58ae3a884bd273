"""Loading a trained nerfstudio model from its ``config.yml`` for rendering and inversion.

nerfstudio's own ``eval_setup`` does not fit: it looks for checkpoints where the run was first written
rather than beside ``config.yml``, exits the process when they are missing, cannot read its checkpoints
under torch >= 2.6, re-runs the dataparser (so it needs the training images) and builds LPIPS, which
downloads AlexNet. Here only the model is built: its scene box and sizes come from the checkpoint, so a
run folder that was moved, copied to another machine or separated from its training data still loads.
"""

import json
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import yaml
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.base_model import Model

from nerfinv_plugin.model.contraction import use_max_norm_contraction
from nerfinv_plugin.model.hash_kernel import use_density_kernel, use_hash_kernel
from nerfinv_plugin.model.loaded import LoadedModel, ModelLoadError
from nerfinv_plugin.model.nerfacto_tiny import lpips_disabled
from nerfinv_plugin.model.render import check_renders

Device = Literal["auto", "cpu", "cuda"]


def resolve_device(device: Device) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ModelLoadError("--device cuda was asked for but torch sees no CUDA device; use cpu or auto")
    return torch.device(device)


def read_config(config_path: Path) -> TrainerConfig:
    config_path = Path(config_path)
    if not config_path.is_file():
        raise ModelLoadError(f"no config file at {config_path}: pass the config.yml that ns-train wrote in "
                             "outputs/<experiment>/<method>/<timestamp>/")
    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    except (yaml.YAMLError, UnicodeDecodeError, AttributeError, ModuleNotFoundError) as err:
        raise ModelLoadError(f"{config_path} is not a readable nerfstudio config ({type(err).__name__}: "
                             f"{str(err).splitlines()[0]}); is the plugin that trained it installed?") from err
    if not isinstance(config, TrainerConfig):
        raise ModelLoadError(f"{config_path} is not a nerfstudio config.yml (it holds a "
                             f"{type(config).__name__}); pass the config.yml written by ns-train")
    return config


def find_checkpoint(config_path: Path, config: TrainerConfig, step: int | None) -> Path:
    """The checkpoint beside ``config.yml`` (not where the run was first written): the latest, or ``step``."""
    folder = Path(config_path).parent / config.relative_model_dir
    found = sorted(folder.glob("step-*.ckpt"))
    if step is not None:
        found = [p for p in found if p.name == f"step-{step:09d}.ckpt"]
    if not found:
        which = f"step-{step:09d}.ckpt" if step is not None else "step-*.ckpt"
        raise ModelLoadError(f"no checkpoint {which} in {folder}: copy the run's nerfstudio_models/ folder "
                             "next to config.yml, or train until a checkpoint is saved")
    return found[-1]


def read_dataparser_transform(config_path: Path) -> tuple[np.ndarray, float]:
    path = Path(config_path).parent / "dataparser_transforms.json"
    if not path.is_file():
        raise ModelLoadError(f"missing {path}: ns-train writes it beside config.yml; without it dataset "
                             "poses cannot be mapped into the model frame")
    data = json.loads(path.read_text())
    transform = np.eye(4)
    transform[:3, :4] = np.asarray(data["transform"], dtype=np.float64)
    return transform, float(data["scale"])


def _model_state(pipeline_state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    state = {}
    for key, value in pipeline_state.items():
        key = key.removeprefix("module.")
        # LPIPS weights (stock nerfacto) are a metric, not part of the radiance field.
        if key.startswith("_model.") and not key.startswith("_model.lpips."):
            state[key.removeprefix("_model.")] = value
    return state


def _num_train_data(state: dict[str, torch.Tensor]) -> int:
    """Training-image count, needed to size per-image embeddings; read off the tensors that depend on it."""
    for key, value in state.items():
        if key.endswith("embedding_appearance.embedding.weight") or key.endswith("pose_adjustment"):
            return int(value.shape[0])
    return 1


def restore_step_state(model: Model, step: int) -> None:
    """Put the model's step-dependent settings where training left them (nerfacto anneals its proposal
    weights over the first iterations; splatfacto raises its spherical-harmonics degree). Training sets
    them in callbacks run before each iteration, which nerfstudio's loader never runs: a short run then
    renders differently after loading than it did while training."""
    model.update_to_step(step)
    attributes = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=None)
    try:
        for callback in model.get_training_callbacks(attributes):
            if TrainingCallbackLocation.BEFORE_TRAIN_ITERATION in callback.where_to_run:
                callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    except AttributeError:
        # splatfacto wires its callbacks to the optimizers; what its rendering reads is ``step``.
        model.step = step
    # nerfacto's proposal sampler counts steps in a callback run after each training iteration; loaded, its count
    # starts at 0, and below step 10 it evaluates the proposal networks with autograd recording for a training
    # update that never comes (their densities only place the samples, whose depths it detaches). At the
    # trained step it evaluates them under no_grad, as training did there: the same numbers, no dead graph.
    sampler = getattr(model, "proposal_sampler", None)
    if sampler is not None and callable(getattr(sampler, "step_cb", None)):
        sampler.step_cb(step)


def load_model(config_path: Path, step: int | None = None, device: Device = "auto") -> LoadedModel:
    """Build the model a ``config.yml`` describes, load its checkpoint, and freeze it in eval mode."""
    config_path = Path(config_path)
    config = read_config(config_path)
    checkpoint = find_checkpoint(config_path, config, step)
    transform, scale = read_dataparser_transform(config_path)
    torch_device = resolve_device(device)
    try:
        saved = torch.load(checkpoint, map_location="cpu", weights_only=False)
        state = _model_state(saved["pipeline"])
    except (RuntimeError, KeyError, EOFError, OSError) as err:
        raise ModelLoadError(f"cannot read checkpoint {checkpoint}: {err}") from err
    aabb = state.get("field.aabb", torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    with lpips_disabled():
        model = config.pipeline.model.setup(scene_box=SceneBox(aabb=aabb), num_train_data=_num_train_data(state),
                                            metadata={}, device=torch_device, grad_scaler=None)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise ModelLoadError(f"checkpoint {checkpoint} does not match the model in {config_path}: "
                             f"{str(err).splitlines()[0]}") from err
    use_hash_kernel(model)  # the compiled kernel once frozen; the fused torch forward otherwise
    use_density_kernel(model)  # the proposal networks' whole forward, where they are evaluated without gradients
    use_max_norm_contraction(model)
    model.to(torch_device).eval().requires_grad_(False)
    result = LoadedModel(model, config, checkpoint, int(saved.get("step", 0)), torch_device, transform, scale)
    # First: for CUDA-only models, step callbacks already try to build CUDA kernels.
    result.chunk_rays = check_renders(result)
    restore_step_state(model, result.step)
    return result
