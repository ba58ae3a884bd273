"""Choosing which pixels of the observed image to render (thesis section 3.2).

Keypoints are detected once per frame (``prepare``); each iteration then draws a fresh set of pixels
(``sample``). Where a strategy runs out of pixels it fills up with random ones, as the thesis does.
"""

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

Strategy = Literal["random", "interest_point", "interest_region"]


def sift_keypoints(image: np.ndarray) -> np.ndarray:
    """SIFT keypoint positions [K, 2] as integer (row, col) of an RGB or grey ``uint8`` image, unique."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    points = cv2.SIFT_create().detect(grey, None)
    if not points:
        return np.zeros((0, 2), dtype=np.int64)
    cols_rows = np.array([p.pt for p in points])
    rows = np.clip(np.round(cols_rows[:, 1]), 0, grey.shape[0] - 1)
    cols = np.clip(np.round(cols_rows[:, 0]), 0, grey.shape[1] - 1)
    return np.unique(np.stack([rows, cols], 1).astype(np.int64), axis=0)


@dataclass
class PixelSampler:
    """Draws ``count`` pixels per iteration from one observed image."""

    strategy: Strategy = "interest_region"
    count: int = 256
    kernel_size: int = 5
    """Interest regions: side of the square dilating each keypoint (the thesis' 5x5)."""

    def prepare(self, image: np.ndarray, mask: np.ndarray | None = None) -> "PixelSampler":
        """Detect keypoints in ``image`` [H, W(, 3)] ``uint8``; an optional boolean ``mask`` restricts
        every pixel drawn (the object, say)."""
        height, width = image.shape[:2]
        allowed = np.ones((height, width), bool) if mask is None else np.asarray(mask, bool)
        if allowed.shape != (height, width):
            raise ValueError(f"mask shape {allowed.shape} does not match the image {(height, width)}")
        self.shape = (height, width)
        self.allowed = np.flatnonzero(allowed)
        if len(self.allowed) == 0:
            raise ValueError("the mask leaves no pixel to sample")
        preferred = np.zeros((height, width), np.uint8)
        if self.strategy != "random":
            keypoints = sift_keypoints(image)
            preferred[keypoints[:, 0], keypoints[:, 1]] = 1
            if self.strategy == "interest_region" and self.kernel_size > 1:
                preferred = cv2.dilate(preferred, np.ones((self.kernel_size, self.kernel_size), np.uint8))
        self.preferred = np.intersect1d(np.flatnonzero(preferred), self.allowed)
        return self

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        """``count`` distinct pixels [count, 2] as (row, col): preferred pixels first, random fill after;
        fewer only when the allowed region is smaller than ``count``."""
        take = min(self.count, len(self.preferred))
        chosen = rng.choice(self.preferred, size=take, replace=False) if take else np.zeros(0, np.int64)
        if take < self.count:
            rest = np.setdiff1d(self.allowed, chosen, assume_unique=True)
            fill = rng.choice(rest, size=min(self.count - take, len(rest)), replace=False)
            chosen = np.concatenate([chosen, fill])
        return np.stack(np.unravel_index(chosen, self.shape), 1).astype(np.int64)

    @property
    def keypoint_pixels(self) -> int:
        """How many pixels the strategy prefers (keypoints, or their dilated region) in this frame."""
        return len(self.preferred)
