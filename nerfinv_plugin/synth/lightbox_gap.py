"""How far the lightbox-like domain is from the synthetic one, frame by frame: the PSNR between the two
images of a pose as written, and whether the object mask of :func:`~nerfinv_plugin.initialization.detect.
find_object` survives the lab camera (its IoU with the object's alpha and with the mask found on a clean
render of the same lab lighting)."""

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import mitsuba as mi
import numpy as np

from nerfinv_plugin.initialization.detect import find_object
from nerfinv_plugin.synth.datasets import RenderedTrajectory
from nerfinv_plugin.synth.lab_scene import lab_scene, render_linear
from nerfinv_plugin.synth.render import PinholeCamera, linear_to_srgb
from nerfinv_plugin.synth.scenes import SceneName


@dataclass(frozen=True)
class FrameGap:
    """One pose seen in both domains."""

    trajectory: str
    filename: str
    psnr_db: float
    """PSNR of the lightbox image against the synthetic one (both as written, JPEG), dB."""
    iou_alpha: float
    """IoU of the mask found on the lightbox image with the object's alpha (> 0.5)."""
    iou_clean: float
    """IoU of the mask found on the lightbox image with the mask found on a clean render of the same view
    and lab lighting (sRGB as the training renders, no camera degradation): what the lab camera costs."""
    clean_iou_alpha: float
    """IoU of the clean lab render's mask with the alpha: what the lab lighting alone leaves visible."""
    synthetic_iou_alpha: float
    """IoU of the mask found on the synthetic image with the alpha, for comparison."""


def psnr_db(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR of two ``uint8`` images of the same shape, dB (inf when equal)."""
    if image.shape != reference.shape:
        raise ValueError(f"images of shapes {image.shape} and {reference.shape} cannot be compared")
    mse = float(np.mean((image.astype(np.float64) - reference.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def mask_iou(mask: np.ndarray | None, reference: np.ndarray | None, shape: tuple[int, int]) -> float:
    """Intersection over union of two [H, W] bool masks (None: nothing found); 1 when both are empty."""
    a = np.zeros(shape, bool) if mask is None else mask
    b = np.zeros(shape, bool) if reference is None else reference
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def _read_rgb(path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise OSError(f"cannot read image {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _found(image: np.ndarray) -> np.ndarray | None:
    detection = find_object(image)
    return None if detection is None else detection.mask


def frame_gaps(scene_name: SceneName, seed: int, synthetic: Sequence[RenderedTrajectory],
               lightbox: Sequence[RenderedTrajectory], camera: PinholeCamera, spp: int) -> list[FrameGap]:
    """The gap of every frame of undistorted trajectories written by ``write_shirt_trajectories`` and
    ``write_lightbox_domain`` (same order). The alpha and the clean lab render are rendered again here with
    ``spp`` samples."""
    scene = mi.load_dict(lab_scene(scene_name, seed))
    gaps = []
    for synth, lab in zip(synthetic, lightbox):
        for k, (c2w_cv, synth_path, lab_path) in enumerate(zip(synth.c2w_opencv, synth.image_paths,
                                                                lab.image_paths)):
            synth_image, lab_image = _read_rgb(synth_path), _read_rgb(lab_path)
            linear, alpha = render_linear(scene, c2w_cv, camera, spp, seed=k)
            clean = np.round(linear_to_srgb(linear) * 255).astype(np.uint8)
            shape = alpha.shape
            silhouette, on_lab, on_clean = alpha > 0.5, _found(lab_image), _found(clean)
            gaps.append(FrameGap(synth.name, synth_path.name, psnr_db(lab_image, synth_image),
                                 mask_iou(on_lab, silhouette, shape), mask_iou(on_lab, on_clean, shape),
                                 mask_iou(on_clean, silhouette, shape),
                                 mask_iou(_found(synth_image), silhouette, shape)))
    return gaps
