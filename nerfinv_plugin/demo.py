"""The whole pipeline on the synthetic spacecraft, each stage skipped when a previous run finished it:
render the training set and a roe1 trajectory, train nerfacto-tiny, invert the trajectory.

A stage counts as finished only when its marker file exists, written after everything else of the stage,
so an interrupted stage is redone from the start (rendering, training) or resumed (inversion).
"""

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.settings import InvertConfig, RenderConfig, StartConfig
from nerfinv_plugin.model.loading import Device
from nerfinv_plugin.model.nerfacto_tiny import MAX_ITERATIONS
from nerfinv_plugin.results.folder import SUMMARY
from nerfinv_plugin.synth.datasets import (
    TrainingSetSpec,
    speedplus_like_camera,
    write_shirt_trajectories,
    write_training_set,
)
from nerfinv_plugin.synth.trajectories import TrajectorySpec

DONE = "complete"
EXPERIMENT = "nerfinv-demo"
TIMESTAMP = "demo"


@dataclass
class DemoSettings:
    """Sizes chosen so that the three stages fit in 15 minutes on a 2-core CPU."""

    data_dir: Path = Path("data/nerfinv-demo")
    """Where the rendered training set and the SHIRT-format trajectory go."""
    output_dir: Path = Path("outputs")
    """Root of the trained model's and the inversion's run folders."""
    frames: int = 8
    """Frames of the roe1 trajectory (the target spins 4 degrees between frames)."""
    training_iterations: int = MAX_ITERATIONS
    """nerfacto-tiny iterations of 512 rays, its default (3.6-5.3 minutes on 2 cores, by the VM)."""
    iterations: int = 60
    """Gradient iterations per Monte Carlo step of the inversion (the thesis' 60)."""
    device: Device = "auto"
    """Where to render during inversion."""
    seed: int = 0
    """Seeds the rendered scene, the trajectory and the inversion."""
    training_set: TrainingSetSpec = field(default_factory=TrainingSetSpec)
    starts: StartConfig = field(default_factory=StartConfig)
    """Where the inversion starts: the view bank, as the bare ns-invert does."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """How rays are sampled: bounded to the object's extent read off the model, as the bare ns-invert does."""

    @property
    def trajectory(self) -> Path:
        return self.data_dir / "shirt" / "roe1"

    @property
    def model_config(self) -> Path:
        return self.output_dir / EXPERIMENT / "nerfacto-tiny" / TIMESTAMP / "config.yml"

    @property
    def run_dir(self) -> Path:
        return self.output_dir / EXPERIMENT / "nerfinv" / TIMESTAMP

    def inversion(self) -> InvertConfig:
        """The inversion the demo runs: what the bare ``ns-invert`` command does, from nothing (starting poses
        from the model's view bank, rays bounded to the object's extent read off the model)."""
        return InvertConfig(
            load_config=self.model_config, sequence=str(self.trajectory), name=EXPERIMENT, timestamp=TIMESTAMP,
            output_dir=self.output_dir, device=self.device, seed=self.seed,
            starts=self.starts, render=self.render, optimizer=OptimizerConfig(iterations=self.iterations))


def data_rendered(settings: DemoSettings) -> bool:
    return (settings.data_dir / DONE).is_file()


def model_trained(settings: DemoSettings) -> bool:
    return (settings.model_config.parent / DONE).is_file()


def inversion_finished(settings: DemoSettings) -> bool:
    return (settings.run_dir / SUMMARY).is_file()


def render_data(settings: DemoSettings, step: Callable[[], None]) -> None:
    """Render the training set and the trajectory, then mark the data complete."""
    spec = settings.training_set
    write_training_set(settings.data_dir, "tango", spec, settings.seed, 64, step)
    camera = speedplus_like_camera(spec.width, spec.height)
    write_shirt_trajectories(settings.data_dir, "tango", [TrajectorySpec(kind="roe1", num_frames=settings.frames)],
                             camera, False, settings.seed, 64, step)
    (settings.data_dir / DONE).write_text("rendered\n")


def train_model(settings: DemoSettings, on_iteration: Callable[[int], None] | None = None) -> None:
    """Train nerfacto-tiny, then mark the run complete."""
    from nerfinv_plugin.model.training import train_nerfacto_tiny

    config = train_nerfacto_tiny(settings.data_dir, settings.output_dir, EXPERIMENT, settings.training_iterations,
                                 timestamp=TIMESTAMP, on_iteration=on_iteration)
    assert config == settings.model_config, (config, settings.model_config)
    (settings.model_config.parent / DONE).write_text("trained\n")
