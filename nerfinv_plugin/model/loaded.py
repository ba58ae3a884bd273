"""What loading a run gives: the frozen model, its frame, and how many rays fit in one chunk."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.base_model import Model


class ModelLoadError(Exception):
    """A run folder that cannot be loaded; the message says what is wrong and how to fix it."""


@dataclass
class LoadedModel:
    """A frozen model and the frame it was trained in."""

    model: Model
    config: TrainerConfig
    checkpoint: Path
    step: int
    device: torch.device
    dataparser_transform: np.ndarray
    """[4, 4]: dataset world -> model world, applied before ``dataparser_scale``."""
    dataparser_scale: float
    chunk_rays: int = 0
    """Rays rendered per chunk under the memory budget as the model was trained; set when the model is
    loaded (how a render samples rays is :class:`nerfinv_plugin.model.render.RenderSettings`, passed to
    each call)."""

    def dataset_to_model(self, c2w: np.ndarray) -> np.ndarray:
        """Camera-to-world poses [..., 4, 4] (OpenGL axes) from the dataset frame into the model frame:
        transform, then scale the translation, as nerfstudio's dataparsers do."""
        out = self.dataparser_transform @ np.asarray(c2w, dtype=np.float64)
        out[..., :3, 3] *= self.dataparser_scale
        return out

    def point_to_model(self, point: np.ndarray) -> np.ndarray:
        """A point [3] from the dataset frame into the model frame (the target centre, say)."""
        pose = np.eye(4)
        pose[:3, 3] = point
        return self.dataset_to_model(pose)[:3, 3]

    def model_to_dataset(self, c2w: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`dataset_to_model`."""
        out = np.array(c2w, dtype=np.float64)
        out[..., :3, 3] /= self.dataparser_scale
        return np.linalg.inv(self.dataparser_transform) @ out
