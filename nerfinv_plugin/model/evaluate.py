"""Image quality of a trained model on held-out views of a Blender-format dataset."""

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from nerfinv_plugin.model.loading import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, render_image


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB of two images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def read_rgb_over_black(path: Path) -> np.ndarray:
    """An image as float RGB in [0, 1]; RGBA images are composited over black, as the model renders."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FileNotFoundError(f"cannot read image {path}")
    image = image.astype(np.float32) / 255.0
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    rgb = image[..., 2::-1] if image.shape[2] >= 3 else np.repeat(image[..., :1], 3, axis=2)
    return rgb * image[..., 3:4] if image.shape[2] == 4 else rgb


@dataclass
class ViewScore:
    file: Path
    psnr: float
    rendered: np.ndarray
    observed: np.ndarray


def evaluate_split(loaded: LoadedModel, data_dir: Path, split: str = "test") -> list[ViewScore]:
    """Render every view of ``transforms_<split>.json`` and score it against its image.

    Poses in the file are in the dataset frame and are mapped through the run's dataparser transform,
    so this also checks that the model frame is what ``dataparser_transforms.json`` says it is.
    """
    meta = json.loads((Path(data_dir) / f"transforms_{split}.json").read_text())
    scores = []
    for frame in meta["frames"]:
        path = Path(data_dir) / (frame["file_path"].removeprefix("./") + ".png")
        observed = read_rgb_over_black(path)
        height, width = observed.shape[:2]
        focal = 0.5 * width / np.tan(0.5 * meta["camera_angle_x"])
        c2w = loaded.dataset_to_model(np.asarray(frame["transform_matrix"], dtype=np.float64))
        rendered = render_image(loaded, c2w, Intrinsics(focal, focal, width / 2, height / 2, width, height))
        scores.append(ViewScore(path, psnr(rendered, observed), rendered, observed))
    return scores
