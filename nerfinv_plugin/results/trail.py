"""The candidate trail of a run folder: what ``ns-invert-view`` needs to replay a run, finished or going on.

Two files, beside the results:

- ``scene.json`` (written once, atomically): the observed camera, every frame's name and true pose when
  known, and the model's training cameras, all in the model frame.
- ``trail.jsonl`` (appended, one line per Monte Carlo step): the candidates every few iterations, their
  final poses and losses, and which of them the step kept. A pose is 7 numbers (scalar-first quaternion,
  then position; model frame, OpenGL camera axes) of about 9 characters each, so a step of 30 candidates
  with 12 snapshots is about 25 kB. Each line goes out in one ``write`` and is flushed; a reader skips a
  last line that has no newline yet, so a run can be replayed while it writes. A resumed run repeats the
  step it lost; the last line of a step wins.
"""

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from nerfinv_plugin.geometry.frames import quat_wxyz_to_rotmat
from nerfinv_plugin.geometry.se3 import rotmat_to_quat
from nerfinv_plugin.results.atomic import write_atomic

SCENE = "scene.json"
TRAIL = "trail.jsonl"
EVERY = 5
"""Iterations between two recorded snapshots of the candidates (the last iteration of a step is always
recorded)."""
DIGITS = 5
"""Decimals kept of each pose number: 1e-5 model units and 1e-5 of a quaternion, far below what a pose
error or a frustum on screen shows."""


def poses_to_rows(c2w: np.ndarray) -> list[list[float]]:
    """[N, 4, 4] camera-to-world poses to N rows ``[qw, qx, qy, qz, x, y, z]``."""
    c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    quats = rotmat_to_quat(torch.as_tensor(c2w[:, :3, :3])).numpy().reshape(-1, 4)
    return np.round(np.concatenate([quats, c2w[:, :3, 3]], 1), DIGITS).tolist()


def rows_to_poses(rows: list[list[float]]) -> np.ndarray:
    """Inverse of :func:`poses_to_rows`: [N, 4, 4]."""
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    for pose, row in zip(poses, rows):
        pose[:3, :3] = quat_wxyz_to_rotmat(np.asarray(row[:4]))
        pose[:3, 3] = row[4:]
    return poses


def _finite_or_none(values: np.ndarray) -> list[float | None]:
    """JSON has no infinity: dropped and pruned candidates' losses become ``null``."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, dtype=np.float64)]


def _losses(values: list[float | None]) -> np.ndarray:
    return np.array([np.inf if v is None else v for v in values], dtype=np.float64)


@dataclass(frozen=True)
class CameraRecord:
    """A camera as a viewer draws it."""

    c2w: list[list[float]]
    """4x4 camera-to-world, model frame, OpenGL axes."""
    fov: float
    """Vertical field of view, radians."""
    aspect: float
    """Width over height."""


@dataclass(frozen=True)
class SceneRecord:
    """What does not change during a run: ``scene.json``."""

    observed: CameraRecord | None
    """The observed camera's field of view (its pose is each frame's truth, or the estimate)."""
    intrinsics: tuple[float, float, float, float]
    """fx, fy, cx, cy of the observed camera (nerfstudio convention: cx = W / 2 when centred), in pixels."""
    width: int
    height: int
    frames: list[str]
    """Names of the frames the run estimates, in order."""
    truths: list[list[list[float]] | None]
    """True 4x4 pose of every frame in the model frame, ``None`` where the sequence has no label."""
    training_cameras: list[CameraRecord] = field(default_factory=list)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "SceneRecord":
        observed = None if data["observed"] is None else CameraRecord(**data["observed"])
        return cls(observed, tuple(data["intrinsics"]), data["width"], data["height"], data["frames"], data["truths"],
                   [CameraRecord(**c) for c in data["training_cameras"]])


@dataclass(frozen=True)
class TrailStep:
    """One Monte Carlo step of the trail: a line of ``trail.jsonl``."""

    step: int
    frame: int
    """Index of the frame among those the run estimates."""
    iterations: list[int]
    """Iterations (0-based) at which the candidates were recorded."""
    poses: list[np.ndarray]
    """[N, 4, 4] candidates at each recorded iteration."""
    losses: list[np.ndarray]
    """[N] their losses on that iteration's pixels (``inf``: dropped or pruned)."""
    final: np.ndarray
    """[N, 4, 4] the candidates at the end of the step."""
    final_losses: np.ndarray
    """[N] ranked on the frame's evaluation pixels."""
    kept: list[int]
    """Indices (into ``final``) of the candidates the step kept, best first."""

    def to_json(self) -> dict:
        return {"step": self.step, "frame": self.frame, "iterations": self.iterations,
                "poses": [poses_to_rows(p) for p in self.poses], "losses": [_finite_or_none(v) for v in self.losses],
                "final": poses_to_rows(self.final), "final_losses": _finite_or_none(self.final_losses),
                "kept": self.kept}

    @classmethod
    def from_json(cls, data: dict) -> "TrailStep":
        return cls(data["step"], data["frame"], data["iterations"], [rows_to_poses(p) for p in data["poses"]],
                   [_losses(v) for v in data["losses"]], rows_to_poses(data["final"]), _losses(data["final_losses"]),
                   data["kept"])


def recorded_iterations(count: int, every: int = EVERY) -> list[int]:
    """Which of ``count`` iterations the trail records: every ``every``-th and the last."""
    return sorted({*range(0, count, every), count - 1}) if count else []


def write_scene(folder: Path, scene: SceneRecord) -> None:
    write_atomic(Path(folder) / SCENE, json.dumps(scene.to_json()))


def read_scene(folder: Path) -> SceneRecord | None:
    """``scene.json``, or ``None`` while the run has not written it (still loading, or an older run)."""
    path = Path(folder) / SCENE
    return SceneRecord.from_json(json.loads(path.read_text())) if path.is_file() else None


def append_step(folder: Path, step: TrailStep) -> None:
    """Append one line in one write, flushed to disk: a reader sees all of it or, without its newline,
    skips it."""
    line = (json.dumps(step.to_json(), separators=(",", ":")) + "\n").encode()
    fd = os.open(Path(folder) / TRAIL, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        os.write(fd, line)
        os.fsync(fd)
    finally:
        os.close(fd)


def read_trail(folder: Path, offset: int = 0) -> tuple[list[TrailStep], int]:
    """Steps of ``trail.jsonl`` from byte ``offset`` on, and the offset to read from next time (past the last
    complete line). A step written again (a resumed run) replaces the earlier one in the viewer, so both
    are returned, in file order."""
    path = Path(folder) / TRAIL
    if not path.is_file():
        return [], offset
    with open(path, "rb") as f:
        f.seek(offset)
        data = f.read()
    complete = data[:data.rfind(b"\n") + 1]
    steps = [TrailStep.from_json(json.loads(line)) for line in complete.splitlines() if line]
    return steps, offset + len(complete)
