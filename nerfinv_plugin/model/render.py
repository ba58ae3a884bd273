"""Rendering a loaded model at camera poses given in the model frame (OpenGL camera axes)."""

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from nerfinv_plugin.model.loading import LoadedModel


def render_image(loaded: LoadedModel, c2w_model: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                 width: int, height: int) -> np.ndarray:
    """Full image [H, W, 3] in [0, 1] at one pose [4, 4]; intrinsics in nerfstudio's convention (pixel
    centres at +0.5, so a centred principal point is cx = W / 2). No gradients: for evaluation."""
    camera = Cameras(
        camera_to_worlds=torch.as_tensor(np.asarray(c2w_model)[None, :3, :4], dtype=torch.float32),
        fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), width=width, height=height,
        camera_type=CameraType.PERSPECTIVE,
    ).to(loaded.device)
    outputs = loaded.model.get_outputs_for_camera(camera)
    return outputs["rgb"].clamp(0, 1).cpu().numpy()
