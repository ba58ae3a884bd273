"""``ns-invert-synth``: render a synthetic scene into a NeRF training set, SHIRT-format trajectories and a
SPEED+-format tree."""

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from nerfinv_plugin.cli import run
from nerfinv_plugin.inversion.validation import SettingsError, check, number, under, whole
from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.synth.camera_images import write_camera_images
from nerfinv_plugin.synth.datasets import (
    TrainingSetSpec,
    speedplus_like_camera,
    write_shirt_trajectories,
    write_training_set,
)
from nerfinv_plugin.synth.lightbox_domain import write_lightbox_domain
from nerfinv_plugin.synth.scenes import SceneName
from nerfinv_plugin.synth.speedplus import write_speedplus
from nerfinv_plugin.synth.trajectories import TrajectoryKind, TrajectoryMotion, TrajectorySpec

TRAINING_SET_RULES = {
    "train-views": whole(0), "val-views": whole(0), "test-views": whole(0), "width": whole(1), "height": whole(1),
    "range-m": number(above=0), "range-jitter": number(at_least=0, below=1),  # ranges stay above 0
}
"""What the options of a :class:`TrainingSetSpec` accept (ns-invert-demo nests one too)."""


@dataclass
class TrajectoryOptions(TrajectoryMotion):
    """Trajectories rendered into ``<out>/shirt`` in the SHIRT layout."""

    kinds: tuple[TrajectoryKind, ...] = ("roe1", "roe2")
    """Which trajectories to render: roe1 holds a constant range while the target spins about its z axis;
    roe2 approaches slowly while the target tumbles about its z and x axes. Empty: none."""
    width: int = 240
    """Image width in pixels (the thesis used 240x150 for SHIRT); the field of view is SPEED+'s."""
    height: int = 150
    """Image height in pixels."""
    distortion: bool = False
    """Pass the images through the SPEED+ lens distortion written in camera.json, as a real camera
    would, so that a loader must undistort them. Without it, camera.json has zero distCoeffs."""
    lightbox: bool = False
    """Also render each trajectory's lightbox-like domain into roeN/lightbox/images (labelled by the same
    roeN.json): a simulated lab, with the lamp turned 40 degrees from the training sun and warmer, no
    earthshine, and a lab camera (exposure, gamma 2.0, bloom, defocus, vignette, read and shot noise,
    JPEG 75), all fixed by issue 13 (docs/synthetic-data.md). Train on the synthetic views only."""


@dataclass
class SpeedPlusOptions:
    """Views rendered into ``<out>/speedplus`` in the SPEED+ layout, for ``ns-train ... speedplus-data``."""

    train: int = 0
    """Views in synthetic/train.json; 0 writes no SPEED+ tree."""
    validation: int = 10
    """Views in synthetic/validation.json (nerfstudio's val and test split)."""
    width: int = 240
    """Image width in pixels; the field of view is SPEED+'s."""
    height: int = 150
    """Image height in pixels."""
    distortion: bool = False
    """Pass the images through the SPEED+ lens distortion written in camera.json."""
    range_m: float = 5.0
    """Camera distance from the object centre (metres)."""
    range_jitter: float = 0.2
    """Ranges are drawn from ``range_m * (1 +- range_jitter)``."""

    @property
    def views(self) -> int:
        return self.train + self.validation if self.train else 0


@dataclass
class Synth:
    """Render a synthetic scene with Mitsuba 3 on the CPU: a NeRF training set (Blender and nerfstudio
    transforms files), camera trajectories in the SHIRT format and, on request, a SPEED+ tree.
    Deterministic for a seed."""

    out: Path
    """Output folder; the training set goes at its top, trajectories under ``shirt/``."""
    scene: SceneName = "tango"
    """tango: spacecraft after the public Tango geometry; toy: texture-rich asymmetric tabletop object;
    satellite: thin parts (solar wings 1 cm thick, a boom, a whip antenna), 1.7 m tip to tip."""
    seed: int = 0
    """Seeds textures, view placement, trajectory attitudes and render noise."""
    spp: int = 64
    """Samples per pixel for the path tracer."""
    training: TrainingSetSpec = field(default_factory=TrainingSetSpec)
    """The training set. Set train-views, val-views and test-views to 0 to render none."""
    camera_images: bool = False
    """Also write the training set as a camera delivers it into <out>/rgb: RGB JPEG images over black
    without alpha and a nerfstudio transforms.json (ns-train nerfacto-tiny nerfstudio-data --data <out>/rgb)."""
    trajectory: TrajectoryOptions = field(default_factory=TrajectoryOptions)
    speedplus: SpeedPlusOptions = field(default_factory=SpeedPlusOptions)

    def main(self) -> None:
        check(self, RULES)
        console = Console()
        t = self.trajectory
        specs = [TrajectorySpec.of(kind, t) for kind in t.kinds]
        n_train = self.training.train_views + self.training.val_views + self.training.test_views
        sp = self.speedplus
        total = n_train + t.num_frames * len(specs) * (2 if t.lightbox else 1) + sp.views
        columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
        with Progress(*columns, console=console) as progress:
            task = progress.add_task(f"rendering {self.scene}", total=total)
            step = lambda: progress.advance(task)  # noqa: E731
            if n_train:
                write_training_set(self.out, self.scene, self.training, self.seed, self.spp, step)
                if self.camera_images:
                    write_camera_images(self.out, self.out / "rgb")
            if specs:
                camera = speedplus_like_camera(t.width, t.height)
                rendered = write_shirt_trajectories(self.out, self.scene, specs, camera, t.distortion,
                                                    self.seed, self.spp, step)
                if t.lightbox:
                    write_lightbox_domain(self.out, self.scene, rendered, camera, t.distortion, self.seed,
                                          self.spp, step)
            if sp.views:
                write_speedplus(self.out / "speedplus", self.scene, sp.train, sp.validation, sp.width, sp.height,
                                sp.distortion, self.seed, self.spp, step, sp.range_m, sp.range_jitter)
        write_atomic(self.out / "synth.json", json.dumps(asdict(self), indent=2, default=str))
        console.print(f"[green]wrote {self.out}[/green]")
        if n_train:
            console.print(f"train a model: ns-train nerfacto-tiny --data {self.out}")
        if n_train and self.camera_images:
            console.print(f"or on camera images: ns-train nerfacto-tiny nerfstudio-data --data {self.out / 'rgb'}")
        if sp.views:
            console.print(f"train on the SPEED+ tree: ns-train nerfacto-tiny speedplus-data --data "
                          f"{self.out / 'speedplus'}")


RULES = {
    "seed": whole(0), "spp": whole(1), **under("training", TRAINING_SET_RULES),
    "trajectory.num-frames": whole(1), "trajectory.frame-spacing-s": number(above=0),
    "trajectory.range-m": number(above=0), "trajectory.end-range-m": number(above=0),
    "trajectory.spin-rate-deg-s": number(), "trajectory.second-rate-deg-s": number(),  # either sense of turn
    "trajectory.width": whole(1), "trajectory.height": whole(1),
    "speedplus.train": whole(0),  # 0: no SPEED+ tree
    "speedplus.validation": whole(1),  # a tree needs validation views: nerfstudio evaluates on them
    "speedplus.width": whole(1), "speedplus.height": whole(1), "speedplus.range-m": number(above=0),
    "speedplus.range-jitter": number(at_least=0, below=1),
}
"""What the numeric options accept (nerfinv_plugin/inversion/validation.py)."""


def entrypoint() -> None:
    run(Synth, "ns-invert-synth", SettingsError, OSError, ValueError)


if __name__ == "__main__":
    entrypoint()
