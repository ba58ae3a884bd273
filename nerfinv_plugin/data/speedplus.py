"""nerfstudio dataparser ``speedplus-data``: train a NeRF on SPEED+ images with their labelled poses.

It reads ``<root>/camera.json``, the labels of one domain and the images they list (docs/speedplus.md). The
training world frame is the Tango body frame, the frame SHIRT and SPEED+ labels place the camera in: no
auto-orientation, no centring, only an optional scale. A model trained here is therefore inverted against
SHIRT labels with nothing but that scale to undo, and ``dataparser_transforms.json`` says exactly that.

nerfstudio imports this module for every ``ns-*`` command (entry point ``nerfstudio.dataparser_configs``),
so it imports nothing heavy and does no work at import time.
"""

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from nerfstudio.cameras.camera_utils import get_distortion_params
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.data.utils.dataparsers_utils import get_train_eval_split_interval
from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from nerfinv_plugin.data import camera_and_labels
from nerfinv_plugin.data.camera_and_labels import CameraFile, label_c2w_opengl
from nerfinv_plugin.data.images import image_size

Domain = Literal["synthetic", "lightbox", "sunlamp"]

SPLITS = ("train", "val", "test")


@dataclass
class SpeedPlusDataParserConfig(DataParserConfig):
    """SPEED+ (camera.json, <domain>/*.json labels, <domain>/images), world frame = Tango body frame."""

    _target: type = field(default_factory=lambda: SpeedPlus)
    """Target class to instantiate."""
    data: Path = Path("data/speedplusv2")
    """SPEED+ root: the folder holding camera.json, synthetic/, lightbox/ and sunlamp/."""
    domain: Domain = "synthetic"
    """synthetic: train on synthetic/train.json, evaluate on synthetic/validation.json. lightbox, sunlamp:
    the hardware-in-the-loop images, whose only labels are <domain>/test.json, split by hil-eval-interval."""
    hil_eval_interval: int = 10
    """lightbox/sunlamp: labels 0, N, 2N, ... of test.json are held out for val/test, the others train
    (nerfstudio-data's eval-interval rule)."""
    subset_list: Path | None = None
    """Text file of training image filenames, one per line (blank lines and #-comments skipped): train
    only on these. The thesis trained on 500 synthetic images without the Earth in the background."""
    subset_count: int | None = None
    """Train on this many images spread evenly over the training labels (after subset-list); deterministic."""
    eval_count: int | None = None
    """Evaluate on this many images spread evenly over the val/test labels; None: all of them.
    synthetic/validation.json lists 11,994 images, which nerfstudio's data managers would all load."""
    scale_factor: float = 1.0
    """Model units per metre: camera positions and the scene box are multiplied by it and
    dataparser_transforms.json records it as the scale. At 1.0 the Tango (within 0.6 m of its origin) fits
    nerfacto's uncontracted unit cube; a model's near/far planes are in model units."""
    scene_box_bound: float = 1.0
    """Half-size of the scene box in metres (scaled by scale-factor); +-1 m holds the ~1 m Tango."""


@dataclass(frozen=True)
class SpeedPlusCamera:
    """The fields of camera.json that define rays: OpenCV intrinsics and lens distortion."""

    width: int
    height: int
    matrix: np.ndarray
    """3x3 OpenCV camera matrix (pixel centres at integer coordinates)."""
    dist_coeffs: np.ndarray
    """OpenCV (k1, k2, p1, p2, k3)."""

    def nerfstudio_distortion(self) -> torch.Tensor:
        """The coefficients in nerfstudio's order (k1, k2, k3, k4, p1, p2), which differs from OpenCV's."""
        k1, k2, p1, p2, k3 = self.dist_coeffs
        return get_distortion_params(k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)


def read_camera(root: Path) -> SpeedPlusCamera:
    """camera.json of a SPEED+ root (:func:`camera_and_labels.read_camera`), with at most OpenCV's 5
    coefficients, the ones nerfstudio can undistort."""
    path = root / "camera.json"
    if not path.is_file():
        raise FileNotFoundError(f"no camera.json in {root}: --data must be the SPEED+ root (the folder holding "
                                f"camera.json, synthetic/, lightbox/, sunlamp/)")
    camera: CameraFile = camera_and_labels.read_camera(path)
    if camera.dist.size > 5:
        raise ValueError(f"{path}: distCoeffs must be OpenCV's (k1, k2, p1, p2[, k3]), got {camera.dist.size} "
                         f"values; nerfstudio's perspective camera models no more")
    return SpeedPlusCamera(camera.width, camera.height, camera.matrix, np.pad(camera.dist, (0, 5 - camera.dist.size)))


def read_labels(root: Path, relative: str) -> list[dict]:
    """A label file checked (:func:`camera_and_labels.read_labels`), so that a bad file fails here, naming
    the label, instead of deep inside training."""
    path = root / relative
    if not path.is_file():
        raise FileNotFoundError(f"no label file {path}: a SPEED+ root holds {relative}; check --data and --domain")
    labels = camera_and_labels.read_labels(path)
    if not labels:
        raise ValueError(f"{path} holds no label; a SPEED+ label file lists the labelled images")
    return labels


def read_subset_list(path: Path) -> list[str]:
    """Filenames from a subset list: one a line, blank lines and #-comments skipped."""
    if not path.is_file():
        raise FileNotFoundError(f"subset list {path} does not exist; give a text file with one image filename a line")
    names = [line.strip() for line in path.read_text().splitlines()]
    names = [name for name in names if name and not name.startswith("#")]
    if not names:
        raise ValueError(f"subset list {path} names no image")
    return names


def evenly_spaced(count: int, total: int) -> np.ndarray:
    """Indices of ``count`` of ``total`` items, each in the middle of its share: label files are in no
    meaningful order, so an even spread is a fair, deterministic sample of them."""
    return (2 * np.arange(count) + 1) * total // (2 * count)


def take_count(labels: list[dict], count: int, option: str, source: str) -> list[dict]:
    if not 1 <= count <= len(labels):
        raise ValueError(f"{option}={count} but {source} offers {len(labels)} labels; choose 1 to {len(labels)}")
    return [labels[i] for i in evenly_spaced(count, len(labels))]


def take_listed(labels: list[dict], names: list[str], list_path: Path, source: str) -> list[dict]:
    """The labels whose filenames are listed, in label-file order."""
    known = {label["filename"] for label in labels}
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ValueError(f"{unknown[0]!r} from subset list {list_path} is not among the training labels of "
                         f"{source}; {len(unknown)} of its {len(names)} names are unknown: fix the list or --domain")
    wanted = set(names)
    return [label for label in labels if label["filename"] in wanted]


def split_labels(config: SpeedPlusDataParserConfig, split: str) -> tuple[list[dict], str]:
    """The labels of one nerfstudio split, and a description of where they come from (for messages)."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; nerfstudio asks for one of {', '.join(SPLITS)}")
    training = split == "train"
    if config.domain == "synthetic":
        relative = "synthetic/train.json" if training else "synthetic/validation.json"
        return read_labels(config.data, relative), relative
    if config.hil_eval_interval < 2:
        raise ValueError(f"hil-eval-interval={config.hil_eval_interval} leaves no training images; use 2 or more")
    relative = f"{config.domain}/test.json"
    labels = read_labels(config.data, relative)
    train, held_out = get_train_eval_split_interval(labels, config.hil_eval_interval)
    part = "training" if training else "held-out"
    source = f"{relative} ({part} part; labels 0, {config.hil_eval_interval}, ... are held out)"
    return [labels[i] for i in (train if training else held_out)], source


def select_labels(config: SpeedPlusDataParserConfig, split: str) -> tuple[list[dict], str]:
    """Apply the subset options: subset-list then subset-count to training, eval-count to val/test."""
    labels, source = split_labels(config, split)
    if split == "train":
        if config.subset_list is not None:
            labels = take_listed(labels, read_subset_list(config.subset_list), config.subset_list, source)
        if config.subset_count is not None:
            labels = take_count(labels, config.subset_count, "subset-count", source)
    elif config.eval_count is not None:
        labels = take_count(labels, config.eval_count, "eval-count", source)
    return labels, source


def image_paths(root: Path, domain: Domain, labels: list[dict], camera: SpeedPlusCamera, source: str) -> list[Path]:
    """Paths of the labelled images, each checked to exist at camera.json's size: nerfstudio would
    otherwise fail late with a shape error, or train on rays of the wrong pixels."""
    paths = []
    for label in labels:
        path = root / domain / "images" / label["filename"]
        if not path.is_file():
            raise FileNotFoundError(f"image {path} listed in {source} does not exist; put the {domain} images "
                                    f"in {path.parent} or train on the ones you have with subset-list")
        size = image_size(path)
        if size != (camera.width, camera.height):
            raise ValueError(f"image {path} is {size[0]}x{size[1]} but camera.json says Nu x Nv = "
                             f"{camera.width}x{camera.height}; use the original images (to train smaller, "
                             f"pass --pipeline.datamanager.camera-res-scale-factor)")
        paths.append(path)
    return paths


@dataclass
class SpeedPlus(DataParser):
    """SPEED+ with the Tango body frame as the training world frame (identity transform, fixed scale)."""

    config: SpeedPlusDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        config = self.config
        if not config.scale_factor > 0:
            raise ValueError(f"scale-factor must be positive (model units per metre), got {config.scale_factor}")
        camera = read_camera(config.data)
        labels, source = select_labels(config, split)
        paths = image_paths(config.data, config.domain, labels, camera, source)
        c2w = np.stack([label_c2w_opengl(label) for label in labels])[:, :3]
        c2w[:, :, 3] *= config.scale_factor
        cameras = Cameras(
            camera_to_worlds=torch.from_numpy(c2w).float(),
            fx=float(camera.matrix[0, 0]),
            fy=float(camera.matrix[1, 1]),
            # OpenCV puts pixel centres at integers, nerfstudio at half-integers.
            cx=float(camera.matrix[0, 2]) + 0.5,
            cy=float(camera.matrix[1, 2]) + 0.5,
            width=camera.width,
            height=camera.height,
            distortion_params=camera.nerfstudio_distortion(),
            camera_type=CameraType.PERSPECTIVE,
        )
        bound = config.scene_box_bound * config.scale_factor
        return DataparserOutputs(
            image_filenames=paths,
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-bound] * 3, [bound] * 3], dtype=torch.float32)),
            dataparser_transform=torch.eye(4)[:3, :],
            dataparser_scale=config.scale_factor,
        )


speedplus_dataparser = DataParserSpecification(
    config=SpeedPlusDataParserConfig(),
    description="SPEED+ (nerfinv): camera.json + <domain> labels and images; world frame = Tango body frame, "
    "lens distortion from distCoeffs, subsets by list or count.",
)
