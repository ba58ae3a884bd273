"""Reading the observed image sequence that ``ns-invert`` inverts, in one of three layouts:

- SHIRT: ``<root>/roeN`` or ``<root>/roeN/<synthetic|lightbox>``, with ``<root>/camera.json`` and the
  labels ``<root>/roeN/roeN.json`` (see /work/shared/reference/datasets.md);
- a Blender split: ``<scene>:<split>`` names ``<scene>/transforms_<split>.json``;
- a folder of PNG / JPEG images with a SHIRT / SPEED+ ``camera.json`` and, optionally, ``poses.json`` in
  the SHIRT label format for the frames whose truth is known.

Every layout ends in the same frames: RGB ``uint8`` over black (the models render over black), undistorted
with camera.json's coefficients, resized to the working resolution, with intrinsics that match, and with
ground-truth poses (where known) as camera-to-world in the dataset frame with OpenGL camera axes. The
dataset frame is converted once here; the model frame is the engine's business.

Bad input raises :class:`SequenceError` with one line that says what is wrong and how to fix it, because
these paths come straight from a command line.
"""

import contextlib
import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from nerfinv_plugin.data.camera_and_labels import (
    CameraFile,
    DataFileError,
    finite_array,
    read_camera,
    read_json,
    read_label_poses,
)
from nerfinv_plugin.data.images import ImageError, read_rgb8
from nerfinv_plugin.model.render import Intrinsics

SequenceKind = Literal["shirt", "blender", "folder"]

SHIRT_DOMAINS = ("synthetic", "lightbox")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
POSES_FILE = "poses.json"
SHIRT_METADATA = "metadata.json"
CAMERA_FILE = "camera.json"

_LAYOUTS = ("a SHIRT trajectory <root>/roeN[/synthetic|/lightbox], a Blender split <scene>:<split> "
            "(for <scene>/transforms_<split>.json), or a folder of .png/.jpg images with camera.json")


class SequenceError(Exception):
    """Bad sequence input; the message is one line saying what is wrong and how to fix it."""


@contextlib.contextmanager
def _sequence_errors() -> Iterator[None]:
    """A bad camera.json or label file is bad sequence input."""
    try:
        yield
    except DataFileError as err:
        raise SequenceError(str(err)) from err


@dataclass
class SequenceFrame:
    name: str
    """Image file name."""
    image: np.ndarray
    """[H, W, 3] ``uint8`` RGB at the working resolution."""
    c2w_true: np.ndarray | None
    """[4, 4] float64 camera-to-world in the dataset frame, OpenGL axes; ``None`` without ground truth."""
    time_s: float | None = None
    """When the frame was taken, seconds after the first frame read (positions in the whole sequence apart,
    times the frame interval); ``None`` when the interval is not known."""


@dataclass
class Sequence:
    frames: list[SequenceFrame]
    intrinsics: Intrinsics
    """nerfstudio-convention pinhole at the working resolution (the images are already undistorted)."""
    kind: SequenceKind
    source: Path
    """SHIRT: the domain folder (``.../roeN/synthetic``, so ``source.name`` is the domain); Blender: the
    transforms file; folder: the folder."""
    native_size: tuple[int, int]
    """(width, height) of the images on disk."""
    frame_interval_s: float | None = None
    """Seconds between consecutive frames of the whole sequence (SHIRT: ``pSim.cam_step`` of
    ``metadata.json``, or the one given); ``None``: not known."""

    @property
    def has_truth(self) -> bool:
        return all(frame.c2w_true is not None for frame in self.frames)


@dataclass(frozen=True)
class _Entry:
    """A frame before its image is read, so that a frame range costs nothing for the frames it skips."""

    name: str
    path: Path
    c2w_true: np.ndarray | None


CameraForSize = Callable[[Path, tuple[int, int]], CameraFile]
"""The camera of a sequence given its first image and that image's (width, height): camera.json fixes the
size and checks it; a Blender split's camera follows from the size."""


@dataclass(frozen=True)
class _Listing:
    kind: SequenceKind
    source: Path
    index: Path
    """The file (or folder) that lists the frames, named when one of them is missing."""
    entries: list[_Entry]
    camera: CameraForSize
    frame_interval_s: float | None = None
    """What the layout says about the frames' spacing in time (SHIRT's metadata.json)."""


def read_sequence(spec: str | Path, start: int = 0, stop: int | None = None, stride: int = 1,
                  resolution: tuple[int, int] | None = None, camera: Path | None = None,
                  frame_interval_s: float | None = None) -> Sequence:
    """Frames ``start:stop:stride`` of the sequence ``spec`` at ``resolution`` (width, height; native if
    ``None``). ``camera`` replaces the camera.json a SHIRT tree or an image folder would be read with.
    ``frame_interval_s`` gives the seconds between consecutive frames of the whole sequence (the frames'
    ``time_s``); unset, SHIRT's metadata.json gives it, and other layouts have no timestamps."""
    _check_range(spec, start, stop, stride)
    if resolution is not None and not (len(resolution) == 2 and all(int(v) == v > 0 for v in resolution)):
        raise SequenceError(f"invalid resolution {resolution} for {spec}; give (width, height) as two positive "
                            "integers, or none to keep the images' own size")
    with _sequence_errors():
        listing = _list_frames(spec, None if camera is None else Path(camera))
    if not listing.entries:
        raise SequenceError(f"{listing.index} lists no frames; point to a sequence with at least one image")
    if frame_interval_s is not None:
        if not (np.isfinite(frame_interval_s) and frame_interval_s > 0):
            raise SequenceError(f"frame interval {frame_interval_s} s for {spec}; give a positive number of seconds")
        listing = dataclasses.replace(listing, frame_interval_s=float(frame_interval_s))
    selected = listing.entries[start:stop:stride]
    if not selected:
        raise SequenceError(f"frames {start}:{'' if stop is None else stop}:{stride} select nothing from the "
                            f"{len(listing.entries)} frames of {listing.source}; choose a start below "
                            f"{len(listing.entries)} and a stop above the start")
    return _load(listing, selected, range(len(listing.entries))[start:stop:stride], resolution)


def shirt_trajectory_poses(spec: str | Path) -> tuple[str, dict[str, np.ndarray]]:
    """The labelled poses of every trajectory in the SHIRT root that ``spec`` (``root/roeN`` or
    ``root/roeN/<domain>``) belongs to, as camera-to-body poses [F, 4, 4] with OpenGL axes in file order,
    keyed by trajectory name; and the name of ``spec``'s own trajectory."""
    path = Path(spec)
    trajectory = path if _is_shirt_trajectory(path) else path.parent
    if not _is_shirt_trajectory(trajectory):
        raise SequenceError(f"{spec} is not a SHIRT trajectory (root/roeN with roeN/roeN.json); poses from SHIRT "
                            "labels need one: use another --starts.source for this sequence")
    with _sequence_errors():
        poses = {folder.name: np.array([c2w for _, c2w in read_label_poses(folder / f"{folder.name}.json")])
                 for folder in sorted(trajectory.parent.iterdir()) if folder.is_dir() and _is_shirt_trajectory(folder)}
    return trajectory.name, poses


def _check_range(spec: str | Path, start: int, stop: int | None, stride: int) -> None:
    if start < 0 or stride < 1 or (stop is not None and stop < 0):
        raise SequenceError(f"invalid frame range start={start} stop={stop} stride={stride} for {spec}; start "
                            "and stop must be >= 0 (stop may be left out) and stride >= 1")


def _list_frames(spec: str | Path, camera: Path | None) -> _Listing:
    """Pick the layout from the path's shape: ``:split`` for Blender, a label file for SHIRT, image files
    for a folder. An existing path wins over a ``:split`` reading, so paths with colons still work."""
    path = Path(spec)
    text = str(spec)
    if not path.exists() and ":" in text:
        scene, split = text.rsplit(":", 1)
        if camera is not None:
            raise SequenceError(f"--camera does not apply to the Blender split {spec}; its camera follows from "
                                "camera_angle_x in the transforms file, so leave --camera out")
        return _blender(Path(scene), split)
    if _is_shirt_trajectory(path.parent) and path.name not in SHIRT_DOMAINS:
        raise SequenceError(f"{path} is not a SHIRT domain; use {path.parent}/synthetic or {path.parent}/lightbox")
    if not path.exists():
        raise SequenceError(f"{path} does not exist; give {_LAYOUTS}")
    if _is_shirt_trajectory(path):
        return _shirt(path, "synthetic", camera)
    if path.is_dir() and _is_shirt_trajectory(path.parent):
        return _shirt(path.parent, path.name, camera)
    if path.is_dir() and _image_files(path):
        return _folder(path, camera)
    raise SequenceError(f"{path} matches no sequence layout; give {_LAYOUTS}{_layout_hint(path)}")


def _layout_hint(path: Path) -> str:
    """Point at the two near misses: a Blender scene without its split, a SHIRT root without a trajectory."""
    if not path.is_dir():
        return ""
    splits = _splits(path)
    if splits:
        return f"; for a Blender split write {path}:{splits[0]} (splits here: {', '.join(splits)})"
    trajectories = sorted(p.name for p in path.iterdir() if p.is_dir() and _is_shirt_trajectory(p))
    if trajectories:
        return f"; for SHIRT name a trajectory, e.g. {path / trajectories[0]}"
    return ""


def _splits(scene: Path) -> list[str]:
    return sorted(p.name[len("transforms_"):-len(".json")] for p in scene.glob("transforms_*.json"))


def _is_shirt_trajectory(path: Path) -> bool:
    return (path / f"{path.name}.json").is_file()


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _shirt(trajectory: Path, domain: str, camera: Path | None) -> _Listing:
    """A SHIRT trajectory shares one label file between its domains; camera.json sits at the dataset root."""
    images = trajectory / domain / "images"
    if not images.is_dir():
        raise SequenceError(f"{images} does not exist; a SHIRT domain keeps its images in <root>/roeN/{domain}/"
                            "images (download or copy that domain)")
    labels_path = trajectory / f"{trajectory.name}.json"
    poses = read_label_poses(labels_path)
    entries = [_Entry(name, images / name, c2w) for name, c2w in poses]
    camera_file = _read_camera(_camera_path(camera, trajectory.parent, "the SHIRT root"))
    return _Listing("shirt", trajectory / domain, labels_path, entries, camera_file,
                    _shirt_frame_interval(trajectory / SHIRT_METADATA))


def _shirt_frame_interval(path: Path) -> float | None:
    """``pSim.cam_step`` of a SHIRT trajectory's metadata.json (5 s in SHIRT v1); ``None`` when the file is
    missing or does not say, which matters only to runs that need timestamps (they say so)."""
    if not path.is_file():
        return None
    try:
        step = read_json(path).get("pSim", {}).get("cam_step")
    except (DataFileError, AttributeError):
        return None
    valid = isinstance(step, int | float) and not isinstance(step, bool) and np.isfinite(step) and step > 0
    return float(step) if valid else None


def _folder(folder: Path, camera: Path | None) -> _Listing:
    """Frames in name order; ``poses.json`` (SHIRT labels) gives truth to the frames it lists, so a folder
    can mix frames with and without truth."""
    files = _image_files(folder)
    truth: dict[str, np.ndarray] = {}
    poses_path = folder / POSES_FILE
    if poses_path.is_file():
        truth = dict(read_label_poses(poses_path))
        names = {p.name for p in files}
        unknown = sorted(set(truth) - names)
        if unknown:
            raise SequenceError(f"{poses_path} lists {unknown[0]}, which is not an image in {folder}; fix the "
                                "filename or remove its entry")
    entries = [_Entry(p.name, p, truth.get(p.name)) for p in files]
    camera_file = _read_camera(_camera_path(camera, folder, "the image folder"))
    return _Listing("folder", folder, folder, entries, camera_file)


def _blender(scene: Path, split: str) -> _Listing:
    """Blender transforms give no principal point: it is the image centre, and the focal length follows from
    camera_angle_x and the image width, so the camera is only known once the first image is read."""
    if not scene.is_dir():
        raise SequenceError(f"{scene} does not exist; give {_LAYOUTS}")
    path = scene / f"transforms_{split}.json"
    if not split or not path.is_file():
        found = _splits(scene)
        choice = f"splits here: {', '.join(found)}" if found else "there are no transforms_*.json files there"
        raise SequenceError(f"{path} does not exist; name an existing split after the colon ({choice})")
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise SequenceError(f"{path} must hold an object with camera_angle_x and frames; fix or regenerate it")
    for key in ("camera_angle_x", "frames"):
        if key not in meta:
            raise SequenceError(f"{path} has no {key!r}; a Blender transforms file needs camera_angle_x and frames")
    angle_x = meta["camera_angle_x"]
    if not isinstance(angle_x, int | float) or not 0 < angle_x < np.pi:
        raise SequenceError(f"{path}: 'camera_angle_x' must be the horizontal field of view in radians, "
                            f"between 0 and pi, not {angle_x!r}")
    if not isinstance(meta["frames"], list):
        raise SequenceError(f"{path}: 'frames' must be a list of {{file_path, transform_matrix}}")
    entries = []
    for i, frame in enumerate(meta["frames"]):
        for key in ("file_path", "transform_matrix"):
            if not isinstance(frame, dict) or key not in frame:
                raise SequenceError(f"frame {i} in {path} has no {key!r}; every frame needs file_path and "
                                    "transform_matrix")
        image = _blender_image_path(scene, str(frame["file_path"]))
        c2w = finite_array(frame["transform_matrix"], (4, 4), f"frame {i} in {path}: 'transform_matrix'",
                           "a 4x4 matrix")
        entries.append(_Entry(image.name, image, c2w))

    def camera(first: Path, size: tuple[int, int]) -> CameraFile:
        width, height = size
        focal = 0.5 * width / np.tan(0.5 * angle_x)
        # OpenCV's centre is half a pixel before nerfstudio's W / 2 (see Intrinsics).
        matrix = np.array([[focal, 0.0, width / 2 - 0.5], [0.0, focal, height / 2 - 0.5], [0.0, 0.0, 1.0]])
        return CameraFile(width, height, matrix, np.zeros(0))

    return _Listing("blender", path, path, entries, camera)


def _blender_image_path(scene: Path, file_path: str) -> Path:
    """Blender's own files leave out the ``.png`` (nerfstudio appends it); other writers keep the suffix."""
    relative = file_path.removeprefix("./")
    if Path(relative).suffix.lower() in IMAGE_SUFFIXES:
        return scene / relative
    return scene / f"{relative}.png"


def _camera_path(explicit: Path | None, folder: Path, where: str) -> Path:
    if explicit is not None:
        if not explicit.is_file():
            raise SequenceError(f"camera file {explicit} does not exist; point --camera to a SHIRT / SPEED+ "
                                "camera.json")
        return explicit
    path = folder / CAMERA_FILE
    if not path.is_file():
        raise SequenceError(f"no {CAMERA_FILE} in {folder} ({where}); put one there or point --camera to one")
    return path


def _read_camera(path: Path) -> CameraForSize:
    """camera.json fixes the image size (Nu x Nv), so every image is checked against it."""
    camera_file = read_camera(path)
    expected = (camera_file.width, camera_file.height)

    def camera(first: Path, size: tuple[int, int]) -> CameraFile:
        if size != expected:
            raise SequenceError(f"image {first} is {size[0]}x{size[1]} but {path} is for {expected[0]}x{expected[1]} "
                                "(Nu x Nv); use the camera.json of these images (--camera) or images of that size")
        return camera_file

    return camera


def _load(listing: _Listing, entries: list[_Entry], positions: range, resolution: tuple[int, int] | None) -> Sequence:
    """Read, undistort and resize each frame in turn, so that memory holds one native image at a time.
    ``positions`` are the entries' places in the whole sequence, which their timestamps follow from."""
    first = _read_frame_image(listing, entries[0])
    native = (first.shape[1], first.shape[0])
    camera = listing.camera(entries[0].path, native)
    remap = _undistorter(camera, native)
    target = native if resolution is None else (int(resolution[0]), int(resolution[1]))
    frames = []
    interval = listing.frame_interval_s
    for i, (entry, position) in enumerate(zip(entries, positions)):
        image = first if i == 0 else _read_frame_image(listing, entry)
        size = (image.shape[1], image.shape[0])
        if size != native:
            raise SequenceError(f"image {entry.path} is {size[0]}x{size[1]} but {entries[0].path} is "
                                f"{native[0]}x{native[1]}; all images of a sequence must have one size")
        if remap is not None:
            image = remap(image)
        if target != native:
            image = cv2.resize(image, target, interpolation=cv2.INTER_AREA)
        time_s = None if interval is None else (position - positions[0]) * interval
        frames.append(SequenceFrame(entry.name, image, entry.c2w_true, time_s))
    intrinsics = Intrinsics.from_opencv(camera.matrix, *native).scaled(*target)
    return Sequence(frames, intrinsics, listing.kind, listing.source, native, interval)


def _read_frame_image(listing: _Listing, entry: _Entry) -> np.ndarray:
    if not entry.path.is_file():
        raise SequenceError(f"image {entry.path} listed in {listing.index} does not exist; restore the file "
                            "or remove its entry")
    try:
        return read_rgb8(entry.path)
    except ImageError as err:
        raise SequenceError(f"{err}; replace it with a readable PNG or JPEG") from err


def _undistorter(camera: CameraFile, size: tuple[int, int]) -> Callable[[np.ndarray], np.ndarray] | None:
    """``cv2.undistort`` with the same camera matrix, its map computed once per sequence instead of once per
    frame (the output is identical)."""
    if not np.any(camera.dist):
        return None
    map1, map2 = cv2.initUndistortRectifyMap(camera.matrix, camera.dist, None, camera.matrix, size, cv2.CV_16SC2)
    return lambda image: cv2.remap(image, map1, map2, cv2.INTER_LINEAR)
