"""Reading observed and held-out images as the models render them: RGB over black.

Any PNG / JPEG a dataset may hold is read the same way: grey becomes three equal channels, 16-bit (and
float) images are scaled by their own full range, and alpha is composited over black, because the models
render empty space black. The sequence reader wants ``uint8`` frames, the scorer floats in [0, 1]; both
come from :func:`rgb_over_black`.
"""

from pathlib import Path

import cv2
import numpy as np
from PIL import Image


class ImageError(ValueError):
    """An image file that cannot be decoded."""


def read_image(path: Path) -> np.ndarray:
    """The image as stored: [H, W] or [H, W, C] with OpenCV's channel order (BGR, BGRA)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"image {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageError(f"cannot decode image {path}")
    return image


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, read from its header only."""
    with Image.open(path) as image:
        return image.size


def rgb_over_black(image: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """RGB in [0, 1] [H, W, 3] of ``dtype`` from an image as :func:`read_image` gives it."""
    full = float(np.iinfo(image.dtype).max) if image.dtype.kind in "ui" else 1.0
    scaled = image.astype(dtype) / full
    if scaled.ndim == 2:
        scaled = scaled[..., None]
    channels = scaled.shape[2]
    rgb = scaled[..., 2::-1] if channels >= 3 else np.repeat(scaled[..., :1], 3, axis=2)
    return rgb * scaled[..., -1:] if channels in (2, 4) else rgb


def read_rgb_over_black(path: Path, dtype: type = np.float32) -> np.ndarray:
    """An image file as float RGB in [0, 1] [H, W, 3], composited over black."""
    return rgb_over_black(read_image(path), dtype)


def read_rgb8(path: Path) -> np.ndarray:
    """An image file as ``uint8`` RGB [H, W, 3] over black (rounded from :func:`rgb_over_black` in float64;
    8-bit images without alpha are taken as they are)."""
    image = read_image(path)
    if image.dtype == np.uint8 and (image.ndim == 2 or image.shape[2] in (1, 3)):
        rgb = np.repeat(image.reshape(*image.shape[:2], 1), 3, axis=2) if image.ndim == 2 or image.shape[2] == 1 \
            else image[..., ::-1]
        return np.ascontiguousarray(rgb)
    return np.clip(np.round(rgb_over_black(image, np.float64) * 255.0), 0, 255).astype(np.uint8)
