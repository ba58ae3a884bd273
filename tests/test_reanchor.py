"""Re-anchoring carried candidates on the observed silhouette (``--reanchor``): against the analytic images
of a sphere, whose silhouette is a disc of radius ``f r / d`` about the projection of its centre."""

import numpy as np
import pytest
import torch

from nerfinv_plugin.inversion.reanchor import ANCHOR_RAYS, lattice, measure_anchor, project_centre, reanchor
from nerfinv_plugin.model.render import Intrinsics

FRAME = Intrinsics(300.0, 300.0, 120.0, 75.0, 240, 150)
CENTRE = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
"""The target centre (model frame)."""


def _camera(offset: tuple[float, float, float], turn_deg: float = 0.0) -> torch.Tensor:
    """A camera at ``CENTRE + offset`` with nerfstudio's axes, turned by ``turn_deg`` about its y axis."""
    a = np.radians(turn_deg)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    c2w[:3, 3] = CENTRE + torch.tensor(offset, dtype=torch.float64)
    return c2w


def _disc(c2w: torch.Tensor, ball: torch.Tensor, radius: float, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """[len(rows), len(cols)] bool: whether the image of a ball of ``radius`` at ``ball`` [3] covers the
    centres of those full-resolution pixels."""
    (centre_px,), depth = project_centre(c2w[None], ball, FRAME)
    r_px = FRAME.fx * radius / float(depth[0])
    x, y = cols + 0.5 - float(centre_px[0]), rows + 0.5 - float(centre_px[1])
    return x[None] ** 2 + y[:, None] ** 2 <= r_px ** 2


def _full() -> tuple[np.ndarray, np.ndarray]:
    return np.arange(FRAME.height), np.arange(FRAME.width)


@pytest.mark.parametrize("beside", [(0.0, 0.0, 0.0), (0.3, 0.15, 0.0)])
def test_a_candidate_too_far_and_off_centre_lands_on_the_observed_silhouette(beside):
    """The truth 5 m away, the candidate 20% farther and 0.25 m aside with the same attitude; the object a
    0.6 m ball centred on the target or 0.34 m beside it (then the silhouette's centroid is not the target's
    projection, and its offset shrinks with the range). After re-anchoring the candidate sees the ball where
    the truth does, and a second candidate carried with it moves by the same change."""
    ball = CENTRE + torch.tensor(beside, dtype=torch.float64)
    truth = _camera((0.0, 0.0, 5.0), turn_deg=3.0)
    best = _camera((0.25, -0.1, 6.0), turn_deg=3.0)
    other = _camera((0.3, -0.1, 6.0), turn_deg=5.0)
    rows, cols, stride = lattice(FRAME)
    assert stride == 3 and len(rows) * len(cols) <= ANCHOR_RAYS
    observed = _disc(truth, ball, 0.6, *_full())[np.ix_(rows, cols)]  # the frame's mask on the lattice
    anchor = measure_anchor(_disc(best, ball, 0.6, rows, cols), observed, rows, cols, stride, FRAME, best, CENTRE)
    assert anchor is not None and abs(anchor.range_scale - 5.0 / 6.0) < 0.02, anchor
    moved = reanchor(torch.stack([best, other]), best, CENTRE, anchor, FRAME)
    assert torch.equal(moved[:, :3, :3], torch.stack([best, other])[:, :3, :3])  # attitudes untouched
    (seen,), _ = project_centre(moved[:1], ball, FRAME)
    (wanted,), _ = project_centre(truth[None], ball, FRAME)
    assert (seen - wanted).abs().max() < 0.5, (seen, wanted)  # pixels
    _, depths = project_centre(moved, CENTRE, FRAME)
    _, before = project_centre(torch.stack([best, other]), CENTRE, FRAME)
    assert torch.allclose(depths / before, torch.full((2,), anchor.range_scale, dtype=torch.float64))
    _, true_depth = project_centre(truth[None], CENTRE, FRAME)
    assert abs(float(depths[0] - true_depth[0])) < 0.05, (depths, true_depth)  # 1% of the range


def test_no_anchor_from_an_empty_silhouette_or_an_implausible_change_of_range():
    rows, cols, stride = lattice(FRAME)
    truth = _camera((0.0, 0.0, 5.0))
    observed = _disc(truth, CENTRE, 0.6, rows, cols)
    empty = np.zeros_like(observed)
    assert measure_anchor(empty, observed, rows, cols, stride, FRAME, truth, CENTRE) is None
    assert measure_anchor(observed, empty, rows, cols, stride, FRAME, truth, CENTRE) is None
    twice = _camera((0.0, 0.0, 10.0))  # the object half the size: a factor 2 is not a frame's change of range
    assert measure_anchor(_disc(twice, CENTRE, 0.6, rows, cols), observed, rows, cols, stride, FRAME, twice,
                          CENTRE) is None
    same = measure_anchor(observed, observed, rows, cols, stride, FRAME, truth, CENTRE)
    assert same.range_scale == 1.0 and np.allclose(same.centre_px, (120.0, 75.0)), same  # where it already is
