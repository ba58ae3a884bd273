"""``ns-invert --viewer``: the inversion drawn while it runs, from the run's :class:`Events`.

The viewer works in the run's own thread, between iterations, and only sends messages (viser broadcasts
them from its own thread): the candidates every few iterations, the kept ones and the model's render at
the best candidate after each step. With no browser connected the messages only replace the previous ones
in viser's buffer, so a run nobody watches pays almost nothing, and a browser that disconnects changes
nothing for the run.
"""

from dataclasses import dataclass, field

import numpy as np
import viser
from nerfstudio.viewer_legacy.server.viewer_utils import get_free_port

from nerfinv_plugin.inversion.optimizer import IterationRecord
from nerfinv_plugin.inversion.session import Events
from nerfinv_plugin.inversion.tracker import Frame, StepRecord
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import RenderSettings, render_image
from nerfinv_plugin.results.records import FrameResult
from nerfinv_plugin.results.trail import EVERY
from nerfinv_plugin.viewer.record import kept_indices, scene_record
from nerfinv_plugin.viewer.scene import IMAGE_WIDTH, InversionScene

DEFAULT_PORT = 7007
"""nerfstudio's ``ViewerConfig.websocket_port_default``."""
HOST = "0.0.0.0"
"""As nerfstudio's ``ViewerConfig.websocket_host``."""


def start_server(port: int | None) -> viser.ViserServer:
    """A viser server on ``port``; unset: 7007, or a free port when that one is taken (as ``ns-train``)."""
    return viser.ViserServer(host=HOST, port=get_free_port(DEFAULT_PORT) if port is None else port, verbose=False)


def viewer_url(server: viser.ViserServer) -> str:
    """The line ``ns-train`` prints for its viewer."""
    return f"Viewer running locally at: http://localhost:{server.get_port()} (listening on {HOST})"


@dataclass
class LiveViewer:
    """Listens to a run and draws it on ``server``."""

    server: viser.ViserServer
    render: bool = True
    """Render the model at the best candidate after every step (a full image at the panel's width)."""
    every: int = EVERY
    """Iterations between two drawings of the candidates."""
    scene: InversionScene | None = None
    frames: list[Frame] = field(default_factory=list)
    loaded_model: LoadedModel | None = None
    settings: RenderSettings | None = None
    step: int = 0
    frame: int = -1
    """The frame shown as observed."""

    def events(self) -> Events:
        return Events(iteration=self.iteration, frame=self.finished, loaded=self.loaded, step_begin=self.step_begin,
                      ranked=self.ranked)

    def loaded(self, loaded: LoadedModel, frames: list[Frame], settings: RenderSettings) -> None:
        self.loaded_model, self.frames, self.settings = loaded, frames, settings
        if self.scene is None:
            self.scene = InversionScene(self.server, scene_record(loaded, frames))

    def step_begin(self, step: int, k: int) -> None:
        self.step = step
        if self.scene is not None and k != self.frame:
            self.frame = k
            frame = self.frames[k]
            self.scene.observed(frame.image, None if frame.c2w_true is None else frame.c2w_true.double().numpy())
            self.scene.show_images(frame.image, None)

    def iteration(self, i: int, record: IterationRecord) -> None:
        if self.scene is None or record.c2w is None:
            return
        if i % self.every == 0:
            self.scene.show_candidates(record.c2w, record.loss)
            best = int(np.argmin(record.loss))
            error = "" if record.error_deg is None else f", rotation error {record.error_deg[best]:.2f} deg"
            self.scene.show_status(f"frame {self.frame + 1} of {len(self.frames)}, step {self.step + 1}, "
                                   f"iteration {i + 1}: best loss {record.loss[best]:.5f}{error}")

    def ranked(self, step: int, record: StepRecord) -> None:
        if self.scene is None:
            return
        result = record.result
        final = result.c2w.detach().cpu().numpy()
        self.scene.show_candidates(final, result.losses.detach().cpu().numpy())
        self.scene.show_kept(final[kept_indices(record)])
        frame = self.frames[record.frame_index]
        if frame.c2w_true is None:
            self.scene.observed(frame.image, record.estimate.double().numpy())
        if self.render:
            self.scene.show_images(frame.image, self._render(record.estimate.double().numpy(), frame))

    def _render(self, c2w: np.ndarray, frame: Frame) -> np.ndarray:
        """The model at ``c2w``, at the panel's width (a larger render would not be seen)."""
        intrinsics = frame.intrinsics
        width = min(IMAGE_WIDTH, intrinsics.width)
        height = max(1, round(intrinsics.height * width / intrinsics.width))
        return render_image(self.loaded_model, c2w, intrinsics.scaled(width, height), self.settings)

    def finished(self, row: FrameResult) -> None:
        if self.scene is not None:
            self.scene.show_estimate(row.index, np.asarray(row.c2w_model))
