"""The silhouette term: the model's accumulation against the observed object mask, on a band about the outline.

A dark, weakly textured spacecraft gives the colour loss little to hold on to, while its outline against the
black background is sharp in every frame. Comparing the model's accumulation (opacity along the ray, 1 on
the object, 0 off it) with the observed foreground mask measures where the outline is. Pixels are drawn
from a band ``band_px`` wide on both sides of the observed outline (the mask dilated minus the mask
eroded): deep inside or far outside the object every candidate near the truth has accumulation 1 or 0, so
those pixels tell candidates apart no better than the colour does, and a band keeps the pixel count small.
The band is fixed by the observed mask, so a candidate whose outline lies more than ``band_px`` beyond the
observed one is seen only through the band pixels it covers (the colour term and the bank handle larger
errors).

Per band pixel the loss is ``(accumulation - inside)**2`` (``inside`` 1 on the mask, 0 off it); a
candidate's silhouette loss is its mean over the band pixels, added to the colour loss times
``silhouette_weight``.

By default (``silhouette_from grey``) the model's silhouette is not its accumulation but its rendered colour
through the detector's own test made smooth (:func:`soft_grey`): a model trained on a black background may
leave dark parts transparent, so its accumulation covers less than the object the detector finds in a frame.
Both the frame's object and the model's colour are then cut at a level nearer the middle of the object's
edges than the detector's threshold (:func:`edge_mask`): the model blurs its outline, the frame's is sharp.
"""

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.initialization.detect import detector_grey
from nerfinv_plugin.inversion.sampling import PixelSampler

EVAL_BAND_PIXELS = 512
"""Band pixels the final ranking of a step reads, spread evenly along the band: fixed by the mask, so that
steps on one frame (and candidates within a step) are ranked on the same pixels."""


def outline_band(mask: np.ndarray, band_px: int) -> np.ndarray:
    """[H, W] bool: pixels within ``band_px`` of the outline of ``mask`` [H, W] bool, inside and outside
    (a square structuring element of side ``2 band_px + 1``, so the band is ``2 band_px`` pixels wide
    where the outline is straight)."""
    if band_px < 1:
        raise ValueError(f"band_px must be at least 1, got {band_px}")
    mask = np.asarray(mask, np.uint8)
    kernel = np.ones((2 * band_px + 1, 2 * band_px + 1), np.uint8)
    outside = cv2.dilate(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    inside = cv2.erode(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return (outside > 0) & (inside == 0)


def edge_mask(image: np.ndarray, mask: np.ndarray, threshold: float, fraction: float) -> tuple[np.ndarray, float]:
    """The object of ``mask`` [H, W] bool cut at a grey level nearer its edges' midpoint, and that level:
    ``max(threshold, fraction x the median grey level on the mask)`` on the detector's grey image of
    ``image`` [H, W, 3] uint8, its holes filled. The model's silhouette is then read at the same level
    (:func:`soft_grey`). Filled, because a dark patch inside the object would add its own outline to the
    band, where a blurred model's texture does not match: with it, twice Adam's iterations ended 1 degree
    worse on the tests' toy (tests/test_pose_from_nothing.py)."""
    grey = detector_grey(image)
    level = max(threshold, fraction * float(np.median(grey[mask])))
    return filled(mask & (grey > level)), level


def filled(mask: np.ndarray) -> np.ndarray:
    """``mask`` [H, W] bool with its holes filled: every pixel not reached from the frame's border through
    pixels off the mask (4-connected) is on it."""
    outside = np.pad(~mask, 1, constant_values=True).astype(np.uint8)
    cv2.floodFill(outside, None, (0, 0), 2)
    return (outside != 2)[1:-1, 1:-1]


def soft_grey(rgb: Tensor, threshold: float, softness: float) -> Tensor:
    """The detector's foreground made differentiable: ``sigmoid((255 max_c rgb - threshold) / softness)`` [R]
    from colours [R, 3] in [0, 1], ``threshold`` and ``softness`` in grey levels (0-255)."""
    return torch.sigmoid((255.0 * rgb.amax(-1) - threshold) / softness)


def silhouette_per_ray(accumulation: Tensor, inside: Tensor) -> Tensor:
    """Loss of each band ray [R]: ``(accumulation - inside)**2`` from accumulation [R] or [R, 1] and the
    observed foreground [R] (1 on the object, 0 off it)."""
    return (accumulation.reshape(-1) - inside.reshape(-1).to(accumulation.dtype)) ** 2


@dataclass(frozen=True)
class BandPixels:
    """Band pixels of one loss evaluation, with what the observed mask says about each."""

    pixels: Tensor
    """[B, 2] (row, col)."""
    inside: Tensor
    """[B] float, 1 on the observed mask, 0 off it."""
    weight: float
    """Factor on the mean silhouette loss, added to the colour loss."""
    threshold: float | None = None
    """Grey level (0-255) the frame's object was cut at (:func:`edge_mask`): the model's silhouette is then its
    colour through :func:`soft_grey` about the same level. None: its accumulation."""
    softness: float = 4.0
    """:func:`soft_grey`'s scale, grey levels."""


@dataclass
class Silhouette:
    """The observed mask of a frame made ready for a step: the band sampler each iteration draws from, and
    the fixed band pixels the ranking reads."""

    inside: Tensor
    """[H, W] float on the model's device: 1 on the observed mask."""
    sampler: PixelSampler
    """Random pixels of the band, ``pixels`` per iteration."""
    eval_pixels: Tensor
    """[E, 2] band pixels for the ranking, evenly spaced along the band."""
    weight: float
    threshold: float | None = None
    """See :attr:`BandPixels.threshold`."""
    softness: float = 4.0

    @classmethod
    def from_mask(cls, mask: np.ndarray, band_px: int, pixels: int, weight: float,
                  device: torch.device | str = "cpu", threshold: float | None = None,
                  softness: float = 4.0) -> "Silhouette | None":
        """None when ``mask`` has no outline (empty, or the whole frame). With ``threshold`` (grey levels) the
        model's silhouette is read off its colour as the detector read the frame's."""
        band = outline_band(mask, band_px)
        if not band.any():
            return None
        sampler = PixelSampler("random", pixels).prepare(np.zeros(band.shape, np.uint8), band)
        where = np.flatnonzero(band)
        if len(where) > EVAL_BAND_PIXELS:
            where = where[np.linspace(0, len(where) - 1, EVAL_BAND_PIXELS).round().astype(np.int64)]
        eval_pixels = np.stack(np.unravel_index(where, band.shape), 1).astype(np.int64)
        inside = torch.as_tensor(np.asarray(mask, bool), dtype=torch.float32, device=device)
        return cls(inside, sampler, torch.as_tensor(eval_pixels, device=device), weight, threshold, softness)

    def band(self, pixels: Tensor) -> BandPixels:
        """The :class:`BandPixels` of ``pixels`` [B, 2]."""
        return BandPixels(pixels, self.inside[pixels[:, 0], pixels[:, 1]], self.weight, self.threshold,
                          self.softness)

    def draw(self, rng: np.random.Generator) -> BandPixels:
        """Fresh band pixels for one iteration."""
        return self.band(torch.as_tensor(self.sampler.sample(rng), device=self.inside.device))
