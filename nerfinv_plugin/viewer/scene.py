"""The viser scene of an inversion, drawn with nerfstudio's viewer conventions: scene units are model units
times ``VISER_NERFSTUDIO_SCALE_RATIO``, and a camera's OpenGL axes turn into viser's OpenCV frustum axes by
a half-turn about x, as ``nerfstudio.viewer.viewer.Viewer.init_scene`` does; training cameras sit under
``/cameras``, as there.

Every node is broadcast (``server.scene``), not sent to a client, so a browser that connects late gets
the whole current scene, and nothing waits for a browser that is slow or gone.

Nodes: ``/cameras/camera_NNNNN`` (training cameras), ``/observed`` (the observed frame, at its true pose
when known, else at the estimate), ``/candidates/NNN`` (coloured by loss: green the best, red the worst,
grey dropped or pruned), ``/kept/NNN`` (the candidates the last Monte Carlo step kept), ``/trajectory/
estimate`` and ``/trajectory/truth`` (points, and a line through them once there are two).
"""

import base64
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import viser
import viser.transforms as vtf
from matplotlib import colormaps
from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

from nerfinv_plugin.results.trail import CameraRecord, SceneRecord

TRAINING_SCALE = 0.03
"""Size of a training camera's frustum, as a fraction of the distance from the scene's centre to the first
known camera (nerfstudio's fixed 0.1 viewer units is too small to see when the cameras are far, as the
range of a SHIRT trajectory puts them)."""
CANDIDATE_SCALE = 0.06
"""The inversion's frustums, larger: they crowd about one pose, and they are what is watched."""
TRAINING_COLOUR = (120, 120, 120)
OBSERVED_COLOUR = (40, 120, 255)
KEPT_COLOUR = (255, 255, 255)
ESTIMATE_COLOUR = (255, 140, 0)
TRUTH_COLOUR = (40, 120, 255)
DROPPED_COLOUR = (90, 90, 90)
IMAGE_WIDTH = 160
"""Width (pixels) of the observed and rendered images in the panel."""


def frustum_pose(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """viser ``(wxyz, position)`` of a model-frame OpenGL camera-to-world pose [4, 4]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    rotation = vtf.SO3.from_matrix(c2w[:3, :3]) @ vtf.SO3.from_x_radians(np.pi)
    return rotation.wxyz, c2w[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO


def loss_colours(losses: np.ndarray) -> list[tuple[int, int, int]]:
    """One colour per candidate: green for the lowest loss to red for the highest, on a log scale (losses
    spread over decades early in a step); grey where the loss is not finite (dropped, pruned)."""
    losses = np.asarray(losses, dtype=np.float64)
    finite = np.isfinite(losses) & (losses > 0)
    if not finite.any():
        return [DROPPED_COLOUR] * len(losses)
    logs = np.log(np.where(finite, losses, 1.0))
    low, high = logs[finite].min(), logs[finite].max()
    share = (logs - low) / (high - low) if high > low else np.zeros_like(logs)
    rgba = colormaps["RdYlGn"](1.0 - share)
    return [tuple(int(255 * c) for c in colour[:3]) if ok else DROPPED_COLOUR for colour, ok in zip(rgba, finite)]


def small(image: np.ndarray) -> np.ndarray:
    """``image`` [H, W, 3] (uint8, or float in [0, 1]) as uint8 at :data:`IMAGE_WIDTH` pixels wide: what is
    sent to the browser."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = (np.clip(image, 0, 1) * 255).round().astype(np.uint8)
    height = max(1, round(image.shape[0] * IMAGE_WIDTH / image.shape[1]))
    return cv2.resize(image, (IMAGE_WIDTH, height), interpolation=cv2.INTER_AREA)


def image_markdown(images: dict[str, np.ndarray]) -> str:
    """Markdown of the named images side by side, as PNG data URLs, with their names below."""
    cells = []
    for name, image in images.items():
        ok, png = cv2.imencode(".png", cv2.cvtColor(small(image), cv2.COLOR_RGB2BGR))
        assert ok, "OpenCV could not encode a PNG"
        cells.append(f"![{name}](data:image/png;base64,{base64.b64encode(png.tobytes()).decode()})")
    return " ".join(cells) + "\n\n" + " | ".join(images)


@dataclass
class InversionScene:
    """Draws one run on a viser server."""

    server: viser.ViserServer
    scene: SceneRecord
    candidates: dict[int, viser.CameraFrustumHandle] = field(default_factory=dict)
    kept: dict[int, viser.CameraFrustumHandle] = field(default_factory=dict)
    estimates: dict[int, np.ndarray] = field(default_factory=dict)
    """Estimated pose of every finished frame, by frame index."""

    def __post_init__(self) -> None:
        # Where the first known camera is, in viewer units: it sets the frustums' size and the first view.
        known = [t for t in self.scene.truths if t is not None] + [c.c2w for c in self.scene.training_cameras]
        self.eye = np.asarray(known[0])[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO if known else np.full(3, 10.0)
        self.unit = max(float(np.linalg.norm(self.eye)), 1e-3)
        for k, camera in enumerate(self.scene.training_cameras):
            self._frustum(f"/cameras/camera_{k:05d}", camera, np.asarray(camera.c2w), TRAINING_COLOUR,
                          TRAINING_SCALE)
        self.server.on_client_connect(self._look_at_scene)
        self.status = self.server.gui.add_markdown("Waiting for the first iteration")
        # Images are data URLs; image_root only silences viser's warning about relative paths.
        self.images = self.server.gui.add_markdown("", image_root=Path.cwd())

    def _look_at_scene(self, client: viser.ClientHandle) -> None:
        """Show a new browser the stretch between the scene's centre (the model frame's origin, where
        nerfstudio's dataparsers put it) and the first known camera, where the candidates gather, from the
        side, z up (nerfstudio orients the scene so)."""
        middle = self.eye / 2
        side = np.cross(self.eye, (0.0, 0.0, 1.0))
        side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-9 else np.array([1.0, 0.0, 0.0])
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = middle + self.unit * (0.8 * side + np.array([0.0, 0.0, 0.3]))
            client.camera.look_at = middle

    def _frustum(self, name: str, camera: CameraRecord, c2w: np.ndarray, colour: tuple[int, int, int],
                 scale: float, image: np.ndarray | None = None) -> viser.CameraFrustumHandle:
        """A frustum ``scale`` times :attr:`unit` large."""
        wxyz, position = frustum_pose(c2w)
        return self.server.scene.add_camera_frustum(name, fov=camera.fov, aspect=camera.aspect,
                                                    scale=scale * self.unit,
                                                    color=colour, image=image, wxyz=wxyz, position=position)

    def observed(self, image: np.ndarray | None, pose: np.ndarray | None) -> None:
        """The observed frame's camera, showing its image, at ``pose`` (its truth, or the estimate)."""
        if pose is not None and self.scene.observed is not None:
            self._frustum("/observed", self.scene.observed, pose, OBSERVED_COLOUR, 1.6 * CANDIDATE_SCALE,
                          None if image is None else small(image))

    def show_candidates(self, poses: np.ndarray, losses: np.ndarray) -> None:
        """The current candidates [N, 4, 4], coloured by loss [N]; nodes of candidates gone are removed."""
        camera = self.scene.observed
        if camera is None:
            return
        with self.server.atomic():
            for k, (pose, colour) in enumerate(zip(poses, loss_colours(losses))):
                self.candidates[k] = self._frustum(f"/candidates/{k:03d}", camera, pose, colour, CANDIDATE_SCALE)
            for k in [k for k in self.candidates if k >= len(poses)]:
                self.candidates.pop(k).remove()

    def show_kept(self, poses: np.ndarray) -> None:
        """The candidates [K, 4, 4] a Monte Carlo step kept, larger and white."""
        camera = self.scene.observed
        if camera is None:
            return
        with self.server.atomic():
            for k, pose in enumerate(poses):
                self.kept[k] = self._frustum(f"/kept/{k:03d}", camera, pose, KEPT_COLOUR, 1.3 * CANDIDATE_SCALE)
            for k in [k for k in self.kept if k >= len(poses)]:
                self.kept.pop(k).remove()

    def show_estimate(self, frame: int, c2w: np.ndarray) -> None:
        """A frame's estimate joins the estimated trajectory, drawn against the truth of the same frames."""
        self.estimates[frame] = np.asarray(c2w, dtype=np.float64)
        frames = sorted(self.estimates)
        self._path("/trajectory/estimate", np.array([self.estimates[k][:3, 3] for k in frames]), ESTIMATE_COLOUR)
        truths = [self.scene.truths[k] for k in frames if self.scene.truths[k] is not None]
        if truths:
            self._path("/trajectory/truth", np.array([np.asarray(t)[:3, 3] for t in truths]), TRUTH_COLOUR)

    def _path(self, name: str, points: np.ndarray, colour: tuple[int, int, int]) -> None:
        points = points * VISER_NERFSTUDIO_SCALE_RATIO
        with self.server.atomic():
            self.server.scene.add_point_cloud(f"{name}/points", points.astype(np.float32),
                                              np.tile(np.array(colour, dtype=np.uint8), (len(points), 1)),
                                              point_size=0.01 * self.unit)
            if len(points) >= 2:
                self.server.scene.add_spline_catmull_rom(f"{name}/line", points, color=colour, line_width=3.0)

    def show_images(self, observed: np.ndarray | None, rendered: np.ndarray | None) -> None:
        """The observed image and the model's render at the best candidate, side by side in the panel."""
        images = {name: image for name, image in (("observed", observed), ("model at the best candidate", rendered))
                  if image is not None}
        self.images.content = image_markdown(images) if images else ""

    def show_status(self, text: str) -> None:
        self.status.content = text
