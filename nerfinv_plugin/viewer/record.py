"""The candidate trail written during a run (``results/trail.py``), and the :class:`Events` that join a
front end's listeners."""

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from nerfinv_plugin.inversion.session import Events, Inversion, InversionError
from nerfinv_plugin.inversion.tracker import Frame, StepRecord
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, RenderSettings
from nerfinv_plugin.results.trail import EVERY, CameraRecord, SceneRecord, TrailStep, append_step, recorded_iterations
from nerfinv_plugin.results.trail import write_scene as write_scene_file

MAX_TRAINING_CAMERAS = 512
"""As nerfstudio's viewer (``ViewerConfig.max_num_display_images``): more frustums only clutter the view."""


def merged(*listeners: Events) -> Events:
    """One :class:`Events` that calls every listener's callback in turn, in the order given."""
    def each(name: str) -> Callable:
        return lambda *args: [getattr(events, name)(*args) for events in listeners] and None

    def bank(views: int) -> Callable[[int], None]:
        progress = [events.bank(views) for events in listeners]
        return lambda done: [report(done) for report in progress] and None

    calls = {f.name: each(f.name) for f in dataclasses.fields(Events) if f.name != "bank"}
    return Events(**calls, bank=bank)


def camera_record(intrinsics: Intrinsics, c2w: np.ndarray) -> CameraRecord:
    return CameraRecord(np.asarray(c2w, dtype=np.float64).tolist(),
                        float(2 * np.arctan(intrinsics.height / (2 * intrinsics.fy))),
                        intrinsics.width / intrinsics.height)


def training_cameras(loaded: LoadedModel, aspect: float) -> list[CameraRecord]:
    """The model's training cameras in the model frame, from its transforms file (Blender or nerfstudio
    format), at most :data:`MAX_TRAINING_CAMERAS` evenly spaced ones; none when the file is not found
    (the viewer then shows the inversion alone). ``aspect`` is used where the file gives no image size."""
    try:
        path = Inversion._training_transforms(loaded)
    except InversionError:
        return []
    meta = json.loads(Path(path).read_text())
    frames = meta["frames"]
    picked = np.linspace(0, len(frames) - 1, min(MAX_TRAINING_CAMERAS, len(frames)), dtype=int) if frames else []
    cameras = []
    for k in picked:
        frame = {**meta, **frames[k]}
        if "fl_y" in frame and "h" in frame:
            fov = 2 * np.arctan(frame["h"] / (2 * frame["fl_y"]))
            ratio = frame.get("w", frame["h"] * aspect) / frame["h"]
        else:
            fov, ratio = 2 * np.arctan(np.tan(frame["camera_angle_x"] / 2) / aspect), aspect
        c2w = loaded.dataset_to_model(np.asarray(frame["transform_matrix"], dtype=np.float64))
        cameras.append(CameraRecord(c2w.tolist(), float(fov), float(ratio)))
    return cameras


def scene_record(loaded: LoadedModel, frames: list[Frame]) -> SceneRecord:
    intrinsics = frames[0].intrinsics
    truths = [None if f.c2w_true is None else f.c2w_true.double().numpy().tolist() for f in frames]
    return SceneRecord(camera_record(intrinsics, np.eye(4)),
                       (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy), intrinsics.width,
                       intrinsics.height, [f.name for f in frames], truths,
                       training_cameras(loaded, intrinsics.width / intrinsics.height))


def kept_indices(record: StepRecord) -> list[int]:
    """The candidates the step kept, best first: the tracker keeps the ``record.kept`` lowest final losses."""
    losses = record.result.losses.detach().cpu().numpy()
    return [int(i) for i in np.argsort(losses, kind="stable")[:record.kept]]


def trail_step(step: int, record: StepRecord, every: int = EVERY) -> TrailStep:
    history = record.result.history
    recorded = [i for i in recorded_iterations(len(history), every) if history[i].c2w is not None]
    return TrailStep(step, record.frame_index, recorded, [history[i].c2w for i in recorded],
                     [history[i].loss for i in recorded], record.result.c2w.detach().cpu().numpy(),
                     record.result.losses.detach().cpu().numpy(), kept_indices(record))


@dataclasses.dataclass
class TrailRecorder:
    """Writes ``scene.json`` once the run has loaded and a ``trail.jsonl`` line after every step."""

    folder: Path
    every: int = EVERY

    def events(self) -> Events:
        return Events(loaded=self.loaded, ranked=self.ranked)

    def loaded(self, loaded: LoadedModel, frames: list[Frame], settings: RenderSettings) -> None:
        write_scene_file(self.folder, scene_record(loaded, frames))

    def ranked(self, step: int, record: StepRecord) -> None:
        append_step(self.folder, trail_step(step, record, self.every))
