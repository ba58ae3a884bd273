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

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from nerfinv_plugin.geometry.frames import label_to_c2w_opencv, opencv_to_opengl
from nerfinv_plugin.model.render import Intrinsics

SequenceKind = Literal["shirt", "blender", "folder"]

SHIRT_DOMAINS = ("synthetic", "lightbox")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
LABEL_KEYS = ("filename", "q_vbs2tango_true", "r_Vo2To_vbs_true")
POSES_FILE = "poses.json"
CAMERA_FILE = "camera.json"

_LAYOUTS = ("a SHIRT trajectory <root>/roeN[/synthetic|/lightbox], a Blender split <scene>:<split> "
            "(for <scene>/transforms_<split>.json), or a folder of .png/.jpg images with camera.json")
# cv2 accepts these numbers of distortion coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]).
_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


class SequenceError(Exception):
    """Bad sequence input; the message is one line saying what is wrong and how to fix it."""


@dataclass
class SequenceFrame:
    name: str
    """Image file name."""
    image: np.ndarray
    """[H, W, 3] ``uint8`` RGB at the working resolution."""
    c2w_true: np.ndarray | None
    """[4, 4] float64 camera-to-world in the dataset frame, OpenGL axes; ``None`` without ground truth."""


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

    @property
    def has_truth(self) -> bool:
        return all(frame.c2w_true is not None for frame in self.frames)


@dataclass(frozen=True)
class _Entry:
    """A frame before its image is read, so that a frame range costs nothing for the frames it skips."""

    name: str
    path: Path
    c2w_true: np.ndarray | None


@dataclass(frozen=True)
class _Camera:
    """OpenCV camera matrix and distortion coefficients of the images on disk."""

    matrix: np.ndarray
    dist: np.ndarray


CameraForSize = Callable[[Path, tuple[int, int]], _Camera]
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


def read_sequence(spec: str | Path, start: int = 0, stop: int | None = None, stride: int = 1,
                  resolution: tuple[int, int] | None = None, camera: Path | None = None) -> Sequence:
    """Frames ``start:stop:stride`` of the sequence ``spec`` at ``resolution`` (width, height; native if
    ``None``). ``camera`` replaces the camera.json a SHIRT tree or an image folder would be read with."""
    _check_range(spec, start, stop, stride)
    if resolution is not None and not (len(resolution) == 2 and all(int(v) == v > 0 for v in resolution)):
        raise SequenceError(f"invalid resolution {resolution} for {spec}; give (width, height) as two positive "
                            "integers, or none to keep the images' own size")
    listing = _list_frames(spec, None if camera is None else Path(camera))
    if not listing.entries:
        raise SequenceError(f"{listing.index} lists no frames; point to a sequence with at least one image")
    selected = listing.entries[start:stop:stride]
    if not selected:
        raise SequenceError(f"frames {start}:{'' if stop is None else stop}:{stride} select nothing from the "
                            f"{len(listing.entries)} frames of {listing.source}; choose a start below "
                            f"{len(listing.entries)} and a stop above the start")
    return _load(listing, selected, resolution)


def shirt_trajectory_poses(spec: str | Path) -> tuple[str, dict[str, np.ndarray]]:
    """The labelled poses of every trajectory in the SHIRT root that ``spec`` (``root/roeN`` or
    ``root/roeN/<domain>``) belongs to, as camera-to-body poses [F, 4, 4] with OpenGL axes in file order,
    keyed by trajectory name; and the name of ``spec``'s own trajectory."""
    path = Path(spec)
    trajectory = path if _is_shirt_trajectory(path) else path.parent
    if not _is_shirt_trajectory(trajectory):
        raise SequenceError(f"{spec} is not a SHIRT trajectory (root/roeN with roeN/roeN.json); poses from SHIRT "
                            "labels need one: use another --starts.source for this sequence")
    poses = {folder.name: np.array([c2w for _, c2w in _read_labels(folder / f"{folder.name}.json")])
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
    poses = _read_labels(labels_path)
    entries = [_Entry(name, images / name, c2w) for name, c2w in poses]
    camera_file = _read_camera(_camera_path(camera, trajectory.parent, "the SHIRT root"))
    return _Listing("shirt", trajectory / domain, labels_path, entries, camera_file)


def _folder(folder: Path, camera: Path | None) -> _Listing:
    """Frames in name order; ``poses.json`` (SHIRT labels) gives truth to the frames it lists, so a folder
    can mix frames with and without truth."""
    files = _image_files(folder)
    truth: dict[str, np.ndarray] = {}
    poses_path = folder / POSES_FILE
    if poses_path.is_file():
        truth = dict(_read_labels(poses_path))
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
    meta = _read_json(path)
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
        c2w = _array(frame["transform_matrix"], (4, 4), f"frame {i} in {path}: 'transform_matrix'", "a 4x4 matrix")
        entries.append(_Entry(image.name, image, c2w))

    def camera(first: Path, size: tuple[int, int]) -> _Camera:
        width, height = size
        focal = 0.5 * width / np.tan(0.5 * angle_x)
        # OpenCV's centre is half a pixel before nerfstudio's W / 2 (see Intrinsics).
        matrix = np.array([[focal, 0.0, width / 2 - 0.5], [0.0, focal, height / 2 - 0.5], [0.0, 0.0, 1.0]])
        return _Camera(matrix, np.zeros(0))

    return _Listing("blender", path, path, entries, camera)


def _blender_image_path(scene: Path, file_path: str) -> Path:
    """Blender's own files leave out the ``.png`` (nerfstudio appends it); other writers keep the suffix."""
    relative = file_path.removeprefix("./")
    if Path(relative).suffix.lower() in IMAGE_SUFFIXES:
        return scene / relative
    return scene / f"{relative}.png"


def _read_json(path: Path) -> object:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise SequenceError(f"cannot read {path} ({err}); fix or regenerate the file") from err


def _array(value: object, shape: tuple[int, ...], where: str, expected: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = np.empty(0)
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise SequenceError(f"{where} must be {expected} of finite numbers, not {value!r}")
    return array


def _read_labels(path: Path) -> list[tuple[str, np.ndarray]]:
    """SHIRT / SPEED+ labels as (filename, camera-to-body pose with OpenGL axes), in file order."""
    labels = _read_json(path)
    if not isinstance(labels, list):
        raise SequenceError(f"{path} must hold a list of labels with {', '.join(LABEL_KEYS)}; fix or regenerate it")
    poses = []
    for i, label in enumerate(labels):
        for key in LABEL_KEYS:
            if not isinstance(label, dict) or key not in label:
                raise SequenceError(f"label {i} in {path} has no {key!r}; every label needs filename, "
                                    "q_vbs2tango_true (scalar-first) and r_Vo2To_vbs_true (metres)")
        q = _array(label["q_vbs2tango_true"], (4,), f"label {i} in {path}: 'q_vbs2tango_true'", "a quaternion")
        r = _array(label["r_Vo2To_vbs_true"], (3,), f"label {i} in {path}: 'r_Vo2To_vbs_true'", "a 3-vector")
        if not np.any(q):
            raise SequenceError(f"label {i} in {path}: 'q_vbs2tango_true' is all zeros; give a unit quaternion")
        poses.append((str(label["filename"]), opencv_to_opengl(label_to_c2w_opencv(q, r))))
    return poses


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
    data = _read_json(path)
    if not isinstance(data, dict):
        raise SequenceError(f"{path} must hold an object with Nu, Nv, cameraMatrix and distCoeffs; fix it")
    for key in ("Nu", "Nv", "cameraMatrix"):
        if key not in data:
            raise SequenceError(f"{path} has no {key!r}; a camera.json needs Nu, Nv, cameraMatrix (and distCoeffs)")
    for key in ("Nu", "Nv"):
        if not isinstance(data[key], int | float) or data[key] != int(data[key]) or data[key] <= 0:
            raise SequenceError(f"{path}: {key!r} must be a positive whole number of pixels, not {data[key]!r}")
    matrix = _array(data["cameraMatrix"], (3, 3), f"{path}: 'cameraMatrix'", "a 3x3 matrix")
    try:
        dist = np.asarray(data.get("distCoeffs", []), dtype=np.float64).ravel()
    except (TypeError, ValueError):
        dist = np.full(1, np.nan)
    if dist.size not in _DIST_LENGTHS or not np.all(np.isfinite(dist)):
        raise SequenceError(f"{path}: 'distCoeffs' must be 4, 5, 8, 12 or 14 numbers (OpenCV's k1 k2 p1 p2 ...), "
                            f"not {data.get('distCoeffs')!r}")
    expected = (int(data["Nu"]), int(data["Nv"]))

    def camera(first: Path, size: tuple[int, int]) -> _Camera:
        if size != expected:
            raise SequenceError(f"image {first} is {size[0]}x{size[1]} but {path} is for {expected[0]}x{expected[1]} "
                                "(Nu x Nv); use the camera.json of these images (--camera) or images of that size")
        return _Camera(matrix, dist)

    return camera


def _load(listing: _Listing, entries: list[_Entry], resolution: tuple[int, int] | None) -> Sequence:
    """Read, undistort and resize each frame in turn, so that memory holds one native image at a time."""
    first = _read_frame_image(listing, entries[0])
    native = (first.shape[1], first.shape[0])
    camera = listing.camera(entries[0].path, native)
    remap = _undistorter(camera, native)
    target = native if resolution is None else (int(resolution[0]), int(resolution[1]))
    frames = []
    for i, entry in enumerate(entries):
        image = first if i == 0 else _read_frame_image(listing, entry)
        size = (image.shape[1], image.shape[0])
        if size != native:
            raise SequenceError(f"image {entry.path} is {size[0]}x{size[1]} but {entries[0].path} is "
                                f"{native[0]}x{native[1]}; all images of a sequence must have one size")
        if remap is not None:
            image = remap(image)
        if target != native:
            image = cv2.resize(image, target, interpolation=cv2.INTER_AREA)
        frames.append(SequenceFrame(entry.name, image, entry.c2w_true))
    intrinsics = Intrinsics.from_opencv(camera.matrix, *native).scaled(*target)
    return Sequence(frames, intrinsics, listing.kind, listing.source, native)


def _read_frame_image(listing: _Listing, entry: _Entry) -> np.ndarray:
    if not entry.path.is_file():
        raise SequenceError(f"image {entry.path} listed in {listing.index} does not exist; restore the file "
                            "or remove its entry")
    return _read_rgb(entry.path)


def _undistorter(camera: _Camera, size: tuple[int, int]) -> Callable[[np.ndarray], np.ndarray] | None:
    """``cv2.undistort`` with the same camera matrix, its map computed once per sequence instead of once per
    frame (the output is identical)."""
    if not np.any(camera.dist):
        return None
    map1, map2 = cv2.initUndistortRectifyMap(camera.matrix, camera.dist, None, camera.matrix, size, cv2.CV_16SC2)
    return lambda image: cv2.remap(image, map1, map2, cv2.INTER_LINEAR)


def _read_rgb(path: Path) -> np.ndarray:
    """``uint8`` RGB of any PNG / JPEG: grey becomes three equal channels, 16-bit is scaled down, and alpha
    is composited over black, as the models render (like ``model.evaluate.read_rgb_over_black``)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SequenceError(f"cannot decode image {path}; replace it with a readable PNG or JPEG")
    if image.ndim == 2:
        image = image[..., None]
    channels = image.shape[2]
    rgb = np.repeat(image[..., :1], 3, axis=2) if channels <= 2 else image[..., 2::-1]
    full = float(np.iinfo(image.dtype).max)
    if channels in (2, 4):
        rgb = rgb * (image[..., -1:] / full)
    if rgb.dtype != np.uint8:
        rgb = np.clip(np.round(rgb * (255.0 / full)), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(rgb)
