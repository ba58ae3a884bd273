"""``ns-invert-view RUN_DIR``: a run drawn again from its files (``scene.json``, ``trail.jsonl``,
``results.jsonl``), while it runs or after it ended. Lines the run appends later are drawn as they come."""

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import viser

from nerfinv_plugin.data.sequences import SequenceError, read_sequence
from nerfinv_plugin.inversion.session import bound_rays
from nerfinv_plugin.inversion.settings import read_config
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.model.render import Intrinsics, RenderSettings, render_image
from nerfinv_plugin.results.folder import CONFIG, RunFolder
from nerfinv_plugin.results.trail import SCENE, TrailStep, read_scene, read_trail
from nerfinv_plugin.viewer.scene import IMAGE_WIDTH, InversionScene


class ReplayError(Exception):
    """A folder that cannot be replayed; the message says why and what to do."""


@dataclass
class Replay:
    """Draws the steps of the run in ``folder`` on ``server``, ``interval_s`` apart for each recorded
    snapshot of the candidates."""

    folder: Path
    scene: InversionScene
    interval_s: float = 0.1
    model: LoadedModel | None = None
    """When given, the model is rendered at the best candidate of every step."""
    settings: RenderSettings | None = None
    images: list[np.ndarray] | None = None
    offset: int = 0
    steps_drawn: int = 0
    frames_drawn: set[int] = field(default_factory=set)

    @classmethod
    def open(cls, folder: Path, server: viser.ViserServer, interval_s: float = 0.1, render: bool = False,
             device: str = "cpu", warn=print) -> "Replay":
        """The run in ``folder``; its observed images are read again from its sequence (and left out, with a
        warning, when it has moved). ``render`` loads the model to render it at the best candidates."""
        folder = Path(folder)
        if not (folder / CONFIG).is_file():
            raise ReplayError(f"{folder} is not an ns-invert run folder (no {CONFIG}); give the folder printed "
                              "when the run started")
        if not (folder / SCENE).is_file():
            raise ReplayError(f"{folder} has no {SCENE} yet: the run is still loading (try again in a moment) or "
                              "was made before ns-invert recorded candidate trails (run it again)")
        config = read_config(folder / CONFIG)
        images = None
        try:
            sequence = read_sequence(config.sequence, config.start, config.stop, config.stride, config.resolution,
                                     config.camera)
            images = [f.image for f in sequence.frames]
        except SequenceError as err:
            warn(f"the observed images are not shown: {err}")
        model, settings = None, None
        if render:
            model = load_model(config.load_config, device=device)
            centre = torch.as_tensor(model.point_to_model(np.asarray(config.target)), dtype=torch.float32)
            settings, _ = bound_rays(model, centre, config.render)  # the run's own render settings
        return cls(folder, InversionScene(server, read_scene(folder)), interval_s, model, settings, images)

    def play_new(self) -> int:
        """Draw the steps written since the last call; return how many."""
        steps, self.offset = read_trail(self.folder, self.offset)
        for step in steps:
            self._step(step)
        return len(steps)

    def complete(self) -> bool:
        """Whether the run has ended (``summary.json`` written)."""
        return RunFolder(self.folder).summary() is not None

    def _step(self, step: TrailStep) -> None:
        scene, record = self.scene, self.scene.scene
        image = None if self.images is None or step.frame >= len(self.images) else self.images[step.frame]
        truth = record.truths[step.frame] if step.frame < len(record.truths) else None
        if truth is not None:
            scene.observed(image, np.asarray(truth))
        for iteration, poses, losses in zip(step.iterations, step.poses, step.losses):
            scene.show_candidates(poses, losses)
            best = int(np.argmin(losses))
            scene.show_status(f"replay of {self.folder.name}: frame {step.frame + 1} of {len(record.frames)}, "
                              f"step {step.step + 1}, iteration {iteration + 1}: best loss {losses[best]:.5f}")
            time.sleep(self.interval_s)
        scene.show_candidates(step.final, step.final_losses)
        scene.show_kept(step.final[step.kept])
        best = step.final[step.kept[0] if step.kept else int(np.argmin(step.final_losses))]
        if truth is None:
            scene.observed(image, best)
        scene.show_images(image, None if self.model is None else self._render(best))
        for row in RunFolder(self.folder).rows():
            if row.index <= step.frame and row.index not in self.frames_drawn:
                self.frames_drawn.add(row.index)
                scene.show_estimate(row.index, np.asarray(row.c2w_model))
        self.steps_drawn += 1

    def _render(self, c2w: np.ndarray) -> np.ndarray:
        record = self.scene.scene
        width = min(IMAGE_WIDTH, record.width)
        height = max(1, round(record.height * width / record.width))
        intrinsics = Intrinsics(*record.intrinsics, record.width, record.height).scaled(width, height)
        return render_image(self.model, c2w, intrinsics, self.settings)
