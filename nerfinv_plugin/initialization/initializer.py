"""What the tracker asks when it knows nothing of the pose, or has lost it: the bank's hypotheses for a
frame, and a check of whether an estimate still puts the object where the frame shows it."""

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.initialization.bank import (
    BankConfig,
    BankEntries,
    cached_bank,
    cached_entries,
    hypotheses,
    hypothesis_poses,
)
from nerfinv_plugin.initialization.detect import Detection
from nerfinv_plugin.initialization.extent import framed_radius
from nerfinv_plugin.model.loaded import LoadedModel, ModelLoadError
from nerfinv_plugin.model.render import Intrinsics, RenderSettings, render

SILHOUETTE_RAYS = 4096
"""At most this many rays render an estimate's silhouette for the lost-object check."""


@dataclass
class Initializer:
    """The bank of a loaded model, ready to match frames."""

    loaded: LoadedModel
    settings: RenderSettings
    """How the bank was rendered (and the lost-object check renders)."""
    centre: np.ndarray
    """[3] object centre, model frame."""
    config: BankConfig
    entries: BankEntries
    cache: Path
    built: bool
    """Whether this run rendered the bank (``False``: read from the cache)."""
    build_s: float

    @classmethod
    def create(cls, loaded: LoadedModel, settings: RenderSettings, centre: np.ndarray, config: BankConfig,
               on_build: Callable[[int], Callable[[int], None]] | None = None,
               radius: float | None = None) -> "Initializer":
        """The bank about ``centre`` (model frame) rendered under ``settings``, framing ``radius`` (model
        units; unset: the sphere ``settings`` bound rays to, or the object's extent read off the model when
        they do not bound them, which measures the density grid)."""
        if radius is None:
            radius = framed_radius(loaded, torch.as_tensor(centre, dtype=torch.float32), settings)
        bank, path, built = cached_bank(loaded, settings, centre, radius, config, on_build)
        entries = cached_entries(bank, path, config)
        if not entries.views:
            raise ModelLoadError(f"the model renders nothing from any of the bank's {config.views} viewpoints about "
                                 "the target: is --target the object's centre, and did the model learn it?")
        return cls(loaded, settings, np.asarray(centre, dtype=np.float64), config, entries, path, built,
                   bank.build_s)

    def poses(self, image: np.ndarray, detection: Detection, intrinsics: Intrinsics, count: int) -> Tensor:
        """The ``count`` best hypotheses [K, 4, 4] (model frame, float32) for the object in ``image``."""
        return hypothesis_poses(hypotheses(self.entries, image, detection, intrinsics, self.centre, count,
                                           self.config))


def rendered_silhouette(loaded: LoadedModel, settings: RenderSettings, c2w: Tensor,
                        intrinsics: Intrinsics) -> np.ndarray:
    """The model's opacity [h, w] (accumulation, or the brightest channel for a model without one) at pose
    ``c2w`` [4, 4], rendered under ``settings`` on a grid of at most :data:`SILHOUETTE_RAYS` pixels that
    covers the frame of ``intrinsics``."""
    factor = max(1, int(np.ceil(np.sqrt(intrinsics.width * intrinsics.height / SILHOUETTE_RAYS))))
    width, height = max(1, intrinsics.width // factor), max(1, intrinsics.height // factor)
    small = intrinsics.scaled(width, height)
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pixels = torch.stack([rows.reshape(-1), cols.reshape(-1)], 1)
    with torch.no_grad():
        out = render(loaded, c2w[None].to(torch.float32), small, pixels, settings)
    opacity = out.accumulation if out.accumulation is not None else out.rgb.amax(-1, keepdim=True)
    return opacity.reshape(height, width).cpu().numpy()


def silhouette_iou(opacity: np.ndarray, mask: np.ndarray) -> float:
    """Overlap of a rendered silhouette (``opacity`` [h, w] over one half, :func:`rendered_silhouette`) with
    the observed ``mask`` [H, W] brought to its grid."""
    height, width = opacity.shape
    rendered = opacity >= 0.5
    observed = cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA) >= 0.5
    union = np.logical_or(rendered, observed).sum()
    return float(np.logical_and(rendered, observed).sum() / union) if union else 0.0
