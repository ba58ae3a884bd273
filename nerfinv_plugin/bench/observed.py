"""One observed frame with its true pose, in the model frame: what the speed and screw benchmarks invert."""

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.data.sequences import SequenceError, read_sequence
from nerfinv_plugin.inversion.starts import inerf_protocol_starts
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics


@dataclass(frozen=True)
class ObservedFrame:
    name: str
    image: np.ndarray
    """[H, W, 3] ``uint8`` RGB at the working resolution."""
    intrinsics: Intrinsics
    truth: Tensor
    """[4, 4] true camera-to-world pose, model frame (float32)."""
    centre: Tensor
    """[3] target centre, model frame (float32)."""
    range_m: float
    """Distance from the true camera to the target centre, dataset metres."""

    def starts(self, count: int, min_deg: float, max_deg: float, shift: float, seed: int) -> Tensor:
        """iNeRF's protocol about the target centre: ``count`` poses [N, 4, 4] turned ``min_deg``-``max_deg``
        off the truth and moved by ``shift`` model units."""
        return inerf_protocol_starts(self.truth, self.centre, count, min_deg, max_deg, shift, seed)


def read_observed(loaded: LoadedModel, spec: str, index: int, target: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  resolution: tuple[int, int] | None = None) -> ObservedFrame:
    """Frame ``index`` of the sequence ``spec`` (``ns-invert``'s ``--sequence`` forms) about the target centre
    ``target`` (dataset frame). Raises :class:`SequenceError` when the frame has no ground truth: the starts
    are placed around it and the errors measured against it."""
    sequence = read_sequence(spec, index, index + 1, 1, resolution)
    frame = sequence.frames[0]
    if frame.c2w_true is None:
        raise SequenceError(f"frame {index} of {spec} has no ground-truth pose; this benchmark needs one (add it to "
                            "poses.json, or use a SHIRT or Blender sequence)")
    centre = np.asarray(target, dtype=np.float64)
    return ObservedFrame(frame.name, frame.image, sequence.intrinsics,
                         torch.as_tensor(loaded.dataset_to_model(frame.c2w_true), dtype=torch.float32),
                         torch.as_tensor(loaded.point_to_model(centre), dtype=torch.float32),
                         float(np.linalg.norm(frame.c2w_true[:3, 3] - centre)))
