"""``nerfacto-tiny``: nerfacto sized for a 2-core CPU with no network.

It is nerfacto (hash-grid field, two proposal networks, the same losses), with three changes that a CPU
machine without internet needs:

- no LPIPS metric: building it downloads AlexNet weights, which fails offline (the metric reports NaN);
- a data manager that caches images in-process instead of spawning loader worker processes;
- the same hash-grid function computed by a faster torch forward (``fused_hash``);
- smaller hash tables, MLPs and sample counts, and proposal sampling between near and far planes;
- planes and the scale of the scene contraction fitted to the training cameras, and densities measured per
  that scale (so that the model learns the same scene whatever scale the dataparser gives it: metres for
  blender-data, a unit cube of cameras for nerfstudio-data), kept in the checkpoint;
- a random background behind RGBA training images and black behind RGB ones (a random background behind
  an image without alpha can only be matched by filling space with black: the model then renders nothing),
  with the pixels of RGB images that surely show the object taught to be opaque and those well away from it
  to be empty;
- the camera optimizer off so that the model frame stays the ground-truth frame, and evaluation/viewer
  settings that never block or render full images often.

nerfstudio imports this module for every ``ns-*`` command (entry point ``nerfstudio.method_configs``),
so it must stay light and must never raise.
"""

import contextlib
import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.model_components.scene_colliders import NearFarCollider
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from nerfinv_plugin.model.fused_hash import use_fused_hash_encoding


class LPIPSUnavailable(torch.nn.Module):
    """Stands in for torchmetrics' LPIPS, whose constructor downloads AlexNet: returns NaN, holds no
    weights, so checkpoints carry no LPIPS entries."""

    def forward(self, *_: torch.Tensor) -> torch.Tensor:
        return torch.tensor(math.nan)


@contextlib.contextmanager
def lpips_disabled() -> Iterator[None]:
    """While active, constructing torchmetrics' LPIPS gives :class:`LPIPSUnavailable` (no download).

    nerfacto imports the class inside ``populate_modules``, so swapping the module attribute is enough;
    the original is restored on exit, also after an exception.
    """
    from torchmetrics.image import lpip

    original = lpip.LearnedPerceptualImagePatchSimilarity
    lpip.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: LPIPSUnavailable()
    try:
        yield
    finally:
        lpip.LearnedPerceptualImagePatchSimilarity = original


class _KeepsMissingBuffers(torch.nn.Module):
    """A module whose buffers an older checkpoint may lack: loading such a checkpoint keeps the values
    the module was built with instead of failing on missing keys."""

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args) -> None:
        for name, value in self._buffers.items():
            state_dict.setdefault(prefix + name, value)
        super()._load_from_state_dict(state_dict, prefix, *args)


class FittedNearFar(_KeepsMissingBuffers, NearFarCollider):
    """nerfstudio's near/far collider whose planes are a buffer, so that planes fitted to the training
    cameras travel with the checkpoint (``config.yml`` is written before the cameras are read)."""

    def __init__(self, near_plane: float, far_plane: float) -> None:
        super().__init__(near_plane=near_plane, far_plane=far_plane)
        self.register_buffer("planes", torch.tensor([near_plane, far_plane]))

    def fit(self, near_plane: float, far_plane: float) -> None:
        self.planes.copy_(torch.tensor([near_plane, far_plane]))
        self.near_plane, self.far_plane = near_plane, far_plane

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args) -> None:
        super()._load_from_state_dict(state_dict, prefix, *args)
        self.near_plane, self.far_plane = (float(v) for v in self.planes)


class ScaledContraction(_KeepsMissingBuffers, SceneContraction):
    """nerfacto's contraction of positions measured in ``unit``s: the cube that the hash grids resolve
    finely (|x| < unit) holds the object whatever scale the dataparser put the scene at.

    ``density_unit`` is the length the fields' densities are measured per: the contraction unit for models
    trained since densities follow it, 1 (model units) for checkpoints written before, which lack it."""

    def __init__(self, unit: float = 1.0) -> None:
        super().__init__(order=float("inf"))
        self.register_buffer("unit", torch.tensor(float(unit)))
        self.register_buffer("density_unit", torch.tensor(1.0))

    def forward(self, positions: Tensor) -> Tensor:
        return super().forward(positions / self.unit)


@dataclass(frozen=True)
class CameraFit:
    """Planes and contraction unit that follow from where the training cameras are (model units)."""

    near: float
    far: float
    unit: float

    @classmethod
    def of(cls, centres: np.ndarray, half_fov_rad: float) -> "CameraFit":
        """For cameras at ``centres`` [N, 3] looking at an object about the origin, whose narrower half
        field of view is ``half_fov_rad``: an object seen whole from the nearest camera lies within
        ``unit = d_min sin(half fov)`` of the origin; rays sample from ``2 unit`` before the nearest camera's
        object to ``2 unit`` beyond the farthest's (never closer than a twentieth of the nearest range)."""
        distances = np.linalg.norm(np.asarray(centres, dtype=np.float64), axis=1)
        d_min, d_max = float(distances.min()), float(distances.max())
        unit = d_min * float(np.sin(half_fov_rad))
        return cls(max(d_min - 2.0 * unit, 0.05 * d_min), d_max + 2.0 * unit, unit)


class NerfactoTinyModel(NerfactoModel):
    """nerfacto whose construction needs no network, with the faster torch hash-grid forward, planes and
    contraction fitted to the training cameras, and a background that suits the training images."""

    config: "NerfactoTinyModelConfig"
    opacity_labels: Tensor | None = None
    """[N, H, W] int8: where each RGB training image surely shows the object and surely shows empty space
    (``opacity`` module), set by the pipeline; ``None`` for RGBA images, whose random background teaches
    opacity."""

    def populate_modules(self) -> None:
        with lpips_disabled():
            super().populate_modules()
        use_fused_hash_encoding(self)
        c = self.config
        self.collider = FittedNearFar(c.near_plane if c.near_plane is not None else 0.05,
                                      c.far_plane if c.far_plane is not None else 1000.0)
        contraction = ScaledContraction(c.contraction_unit if c.contraction_unit is not None else 1.0)
        for field_ in (self.field, *self.proposal_networks):
            field_.spatial_distortion = contraction
        self.register_load_state_dict_post_hook(lambda model, _: model.scale_densities())

    def scale_densities(self) -> None:
        """Measure the fields' densities per ``density_unit`` (the contraction unit): a field's output is
        multiplied by ``average_init_density / density_unit``, so that the same network outputs give the same
        opacity over the object whatever scale the dataparser gave the scene. With densities per model unit,
        nerfstudio-data's unit cube of cameras (the spacecraft's unit 0.17 model units against 0.87 m through
        Blender) left every density six times too thin for the same outputs, from the first step: 3.1 dB lost
        on held-out views after 1,100 iterations (docs/benchmarks.md)."""
        contraction = self.field.spatial_distortion
        for field_ in (self.field, *self.proposal_networks):
            field_.average_init_density = self.config.average_init_density / float(contraction.density_unit)

    def fit_to_cameras(self, centres: np.ndarray, half_fov_rad: float) -> CameraFit:
        """Set the planes and the contraction unit the config leaves unset from the training cameras."""
        fit = CameraFit.of(centres, half_fov_rad)
        c = self.config
        fit = CameraFit(fit.near if c.near_plane is None else c.near_plane,
                        fit.far if c.far_plane is None else c.far_plane,
                        fit.unit if c.contraction_unit is None else c.contraction_unit)
        self.collider.fit(fit.near, fit.far)
        self.field.spatial_distortion.unit.fill_(fit.unit)
        self.field.spatial_distortion.density_unit.fill_(fit.unit)
        self.scale_densities()
        return fit

    def get_loss_dict(self, outputs: dict, batch: dict, metrics_dict: dict | None = None) -> dict:
        with _black_behind_rgb(self, batch["image"]):
            loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training and self.opacity_labels is not None and self.config.object_opacity_loss_mult > 0:
            from nerfinv_plugin.model.opacity import opacity_loss

            image, row, column = batch["indices"].to(self.opacity_labels.device).long().unbind(-1)
            labels = self.opacity_labels[image, row, column].to(outputs["accumulation"].device)
            loss_dict["object_opacity_loss"] = self.config.object_opacity_loss_mult * opacity_loss(
                labels, outputs["accumulation"].squeeze(-1))
        return loss_dict

    def get_metrics_dict(self, outputs: dict, batch: dict) -> dict:
        with _black_behind_rgb(self, batch["image"]):
            return super().get_metrics_dict(outputs, batch)


@contextlib.contextmanager
def _black_behind_rgb(model: NerfactoModel, image: Tensor) -> Iterator[None]:
    """A random background only where the training image has alpha to composite it behind; behind an RGB
    image (what SPEED+, SHIRT and cameras give: the object over black space) the background is black."""
    renderer = model.renderer_rgb
    original = renderer.background_color
    if image.shape[-1] == 3 and original == "random":
        renderer.background_color = "black"
    try:
        yield
    finally:
        renderer.background_color = original


class NerfactoTinyPipeline(VanillaPipeline):
    """nerfstudio's pipeline, which also fits nerfacto-tiny's planes and contraction to the training
    cameras once they are loaded and, for training on RGB images, labels their pixels for the opacity loss."""

    def __init__(self, config: VanillaPipelineConfig, device: str, test_mode: str = "val", *args, **kwargs) -> None:
        super().__init__(config, device, test_mode, *args, **kwargs)
        model = self._model
        if isinstance(model, NerfactoTinyModel) and self.datamanager.train_dataset is not None:
            cameras = self.datamanager.train_dataset.cameras
            centres = cameras.camera_to_worlds[:, :3, 3].cpu().numpy()
            half = torch.minimum(torch.atan(0.5 * cameras.width / cameras.fx),
                                 torch.atan(0.5 * cameras.height / cameras.fy))
            fit = model.fit_to_cameras(centres, float(half.min()))
            CONSOLE.print(f"nerfacto-tiny: near {fit.near:.3f}, far {fit.far:.3f}, contraction unit {fit.unit:.3f} "
                          f"(model units, from {len(centres)} training cameras)")
            dataset = self.datamanager.train_dataset
            over_black = model.config.background_color in ("random", "black")  # the detector's dark background
            training = test_mode == "val"  # ns-train's; ns-eval and ns-viewer load for testing
            wanted = training and over_black and model.config.object_opacity_loss_mult > 0
            first = dataset.get_image_float32(0).numpy() if wanted else None
            if first is not None and first.shape[-1] == 3:
                from nerfinv_plugin.model.opacity import OBJECT, opacity_label_stack  # OpenCV: only for RGB

                rest = (dataset.get_image_float32(i).numpy() for i in range(1, len(dataset)))
                model.opacity_labels = opacity_label_stack(itertools.chain([first], rest))
                share = float((model.opacity_labels == OBJECT).float().mean())
                CONSOLE.print(f"nerfacto-tiny: RGB training images; {share:.1%} of their pixels surely show the "
                              "object and are taught to be opaque, those well away from it to be empty")


@dataclass
class NerfactoTinyPipelineConfig(VanillaPipelineConfig):
    _target: type = field(default_factory=lambda: NerfactoTinyPipeline)


@dataclass
class NerfactoTinyModelConfig(NerfactoModelConfig):
    """nerfacto's options with CPU-sized defaults."""

    _target: type = field(default_factory=lambda: NerfactoTinyModel)
    near_plane: float | None = None
    """Nearest sample during training (model units). Unset: fitted to the training cameras (nearest range
    less twice the contraction unit)."""
    far_plane: float | None = None
    """Farthest sample (model units). Unset: fitted to the training cameras (farthest range plus twice the
    contraction unit)."""
    contraction_unit: float | None = None
    """Half-side of the cube the hash grids resolve finely (model units); space beyond it is contracted.
    Unset: fitted to the training cameras (nearest range times the sine of the narrower half field of
    view, where an object seen whole from the nearest camera lies)."""
    proposal_initial_sampler: Literal["piecewise", "uniform"] = "uniform"
    """Uniform between the planes: the piecewise sampler spends half its samples within 1 unit of the
    camera and leaves an object 5 m away with one or two samples, which it never learns."""
    background_color: Literal["random", "last_sample", "black", "white"] = "random"
    """With RGBA training images, a random background during training teaches opacity (on a fixed black
    one a dark object and a half-transparent one look alike, and colours wash out to grey); behind RGB
    training images it is black (the object over black space). Renders for inversion are over black."""
    implementation: Literal["tcnn", "torch"] = "torch"
    """torch runs everywhere; a tcnn checkpoint cannot be loaded into a torch model, so keep it fixed."""
    num_levels: int = 8
    max_res: int = 256
    log2_hashmap_size: int = 15
    hidden_dim: int = 32
    hidden_dim_color: int = 32
    num_nerf_samples_per_ray: int = 24
    num_proposal_samples_per_ray: tuple[int, ...] = (64, 32)
    proposal_net_args_list: list[dict] = field(default_factory=lambda: [
        {"hidden_dim": 16, "log2_hashmap_size": 14, "num_levels": 5, "max_res": 64, "use_linear": False},
        {"hidden_dim": 16, "log2_hashmap_size": 14, "num_levels": 5, "max_res": 128, "use_linear": False},
    ])
    proposal_warmup: int = 500
    use_appearance_embedding: bool = False
    average_init_density: float = 0.01
    """Scale of the fields' densities, per contraction unit (nerfacto: per model unit), so that a scene
    gets the same opacities at any scale the dataparser puts it at."""
    object_opacity_loss_mult: float = 0.3
    """Weight of the loss that makes the pixels of RGB training images that surely show the object opaque
    and those well away from it empty (the object as ``ns-invert`` finds it in a frame): over black, which RGB
    images of an object in space need behind them, a half-transparent surface looks like an opaque one of
    mixed colour, and black fog like empty space.
    Unused for RGBA images, whose random background teaches opacity, and with a ``last_sample`` or ``white``
    background (an object that is not over black). 0 turns it off."""
    eval_num_rays_per_chunk: int = 4096
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))


def _adam(lr: float, max_steps: int) -> dict:
    return {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr / 20, max_steps=max_steps)}


MAX_ITERATIONS = 2000
"""About 3.7 minutes on 2 CPU cores; 1,100 iterations gave a softer outline that more samples per ray did not
sharpen, and fewer runs under 2 degrees (docs/benchmarks.md, sessions 29-31)."""

nerfacto_tiny = MethodSpecification(
    config=TrainerConfig(
        method_name="nerfacto-tiny",
        max_num_iterations=MAX_ITERATIONS,
        steps_per_save=500,
        steps_per_eval_batch=500,
        steps_per_eval_image=100_000,
        steps_per_eval_all_images=100_000,
        mixed_precision=False,
        machine=MachineConfig(device_type="cuda" if torch.cuda.is_available() else "cpu"),
        pipeline=NerfactoTinyPipelineConfig(
            datamanager=VanillaDataManagerConfig(
                dataparser=BlenderDataParserConfig(alpha_color=None),  # keep RGBA for the random background
                train_num_rays_per_batch=512,
                eval_num_rays_per_batch=1024,
            ),
            model=NerfactoTinyModelConfig(),
        ),
        optimizers={"proposal_networks": _adam(1e-2, MAX_ITERATIONS), "fields": _adam(1e-2, MAX_ITERATIONS)},
        viewer=ViewerConfig(num_rays_per_chunk=4096, quit_on_train_completion=True),
        vis="tensorboard",
    ),
    description="nerfacto sized for a CPU with no network (nerfinv); Blender-format data by default.",
)
