"""``nerfacto-tiny``: nerfacto sized for a 2-core CPU with no network.

It is nerfacto (hash-grid field, two proposal networks, the same losses), with three changes that a CPU
machine without internet needs:

- no LPIPS metric: building it downloads AlexNet weights, which fails offline (the metric reports NaN);
- a data manager that caches images in-process instead of spawning loader worker processes;
- the same hash-grid function computed by a faster torch forward (``fused_hash``);
- smaller hash tables, MLPs and sample counts, proposal sampling between near and far planes that
  bound an object-centred scene, a random background behind RGBA training images, the camera optimizer
  off so that the model frame stays the ground-truth frame, and evaluation/viewer settings that never
  block or render full images often.

nerfstudio imports this module for every ``ns-*`` command (entry point ``nerfstudio.method_configs``),
so it must stay light and must never raise.
"""

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

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


class NerfactoTinyModel(NerfactoModel):
    """nerfacto whose construction needs no network, with the faster torch hash-grid forward."""

    def populate_modules(self) -> None:
        with lpips_disabled():
            super().populate_modules()
        use_fused_hash_encoding(self)


@dataclass
class NerfactoTinyModelConfig(NerfactoModelConfig):
    """nerfacto's options with CPU-sized defaults."""

    _target: type = field(default_factory=lambda: NerfactoTinyModel)
    near_plane: float = 1.0
    """Metres in the scenes ns-invert-synth writes (the object within 1 m of the origin, cameras 1.5 to
    11 m away); scale both planes for other data."""
    far_plane: float = 12.0
    proposal_initial_sampler: Literal["piecewise", "uniform"] = "uniform"
    """Uniform between the planes: the piecewise sampler spends half its samples within 1 unit of the
    camera and leaves an object 5 m away with one or two samples, which it never learns."""
    background_color: Literal["random", "last_sample", "black", "white"] = "random"
    """With RGBA training images, a random background during training teaches opacity (on a fixed black
    one a dark object and a half-transparent one look alike, and colours wash out to grey); renders for
    inversion are then over black, like space."""
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
    eval_num_rays_per_chunk: int = 4096
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))


def _adam(lr: float, max_steps: int) -> dict:
    return {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr / 20, max_steps=max_steps)}


MAX_ITERATIONS = 1100

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
        pipeline=VanillaPipelineConfig(
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
