"""Re-anchoring carried candidates on the camera's motion between two frames (``--reanchor``): against the
analytic images of a ball, whose silhouette is a disc of radius ``f r / sqrt(d^2 - r^2)`` about the projection
of its centre (a disc of ``f r / d`` to well under a pixel here)."""

import numpy as np
import pytest
import torch

from nerfinv_plugin.inversion.reanchor import (
    ANCHOR_RAYS,
    Silhouette,
    align,
    lattice_about,
    motion_anchor,
    project_centre,
    reanchor,
)
from nerfinv_plugin.model.render import Intrinsics

FRAME = Intrinsics(300.0, 300.0, 120.0, 75.0, 240, 150)
CENTRE = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
"""The target centre (model frame)."""
BALL = 0.6
"""The object's radius (m): the ball the frames see."""


def _camera(offset: tuple[float, float, float], turn_deg: float = 0.0) -> torch.Tensor:
    """A camera at ``CENTRE + offset`` with nerfstudio's axes, turned by ``turn_deg`` about its y axis."""
    a = np.radians(turn_deg)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    c2w[:3, 3] = CENTRE + torch.tensor(offset, dtype=torch.float64)
    return c2w


def _disc(c2w: torch.Tensor, ball: torch.Tensor, radius: float, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """[len(ys), len(xs)] bool: whether the image of a ball of ``radius`` at ``ball`` [3] covers the points
    (x, y) (full-resolution pixel coordinates, pixel centres at half-integers)."""
    (centre_px,), depth = project_centre(c2w[None], ball, FRAME)
    r_px = FRAME.fx * radius / float(depth[0])
    x, y = xs - float(centre_px[0]), ys - float(centre_px[1])
    return x[None] ** 2 + y[:, None] ** 2 <= r_px ** 2


def _mask(c2w: torch.Tensor, ball: torch.Tensor = CENTRE) -> np.ndarray:
    """The frame's object mask [H, W] seen from ``c2w``."""
    return _disc(c2w, ball, BALL, np.arange(FRAME.width) + 0.5, np.arange(FRAME.height) + 0.5)


def _silhouette(c2w: torch.Tensor, radius: float = BALL, ball: torch.Tensor = CENTRE) -> Silhouette:
    """The candidate ``c2w``'s render, thresholded, on the lattice ``align`` is given in a run: the ball's image
    (of ``radius``, which the model may get wrong) also where it leaves the frame."""
    lattice = lattice_about(c2w, CENTRE, 1.6 * BALL, FRAME)  # holds the ball beside the centre too
    h, w = lattice.shape
    xs, ys = lattice.x0 + lattice.stride * np.arange(w), lattice.y0 + lattice.stride * np.arange(h)
    return Silhouette(_disc(c2w, ball, radius, xs, ys).astype(np.float32), lattice)


def _depth(c2w: torch.Tensor) -> float:
    return float(project_centre(c2w[None], CENTRE, FRAME)[1][0])


def test_the_lattice_covers_the_objects_sphere_beyond_the_frame():
    best = _camera((1.5, 0.0, 5.0))  # the object's image reaches past the frame's left edge
    lattice = lattice_about(best, CENTRE, 1.2 * BALL, FRAME)
    h, w = lattice.shape
    assert h * w <= ANCHOR_RAYS
    (x, y), r = lattice.centre_px, lattice.radius_px
    assert abs(r - 300.0 * 0.72 / np.sqrt(5.0 ** 2 - 0.72 ** 2)) < 1e-6
    assert x - r < 0 < lattice.x0 + lattice.stride * (w - 1)  # beyond the frame
    assert lattice.x0 <= x - r + lattice.stride and lattice.x0 + lattice.stride * (w - 1) >= x + r - lattice.stride
    assert lattice.y0 <= y - r + lattice.stride and lattice.y0 + lattice.stride * (h - 1) >= y + r - lattice.stride


@pytest.mark.parametrize("beside", [(0.0, 0.0, 0.0), (0.3, 0.15, 0.0)])
def test_candidates_follow_the_cameras_motion_between_two_frames(beside):
    """The camera closes from 6 m to 5 m and slides aside; the best candidate is the last frame's truth. The
    object is a ball on the target centre or 0.34 m beside it (then its image's centre is not the target's
    projection, and its offset grows as the range shrinks). After re-anchoring the candidate sees the ball
    where the new frame does, and a second candidate carried with it moves by the same change of range."""
    ball = CENTRE + torch.tensor(beside, dtype=torch.float64)
    then, now = _camera((0.0, 0.0, 6.0), turn_deg=3.0), _camera((0.2, -0.1, 5.0), turn_deg=3.0)
    other = _camera((0.1, -0.1, 6.2), turn_deg=5.0)
    rendered = _silhouette(then, ball=ball)
    before, after = align(rendered, _mask(then, ball)), align(rendered, _mask(now, ball))
    assert before is not None and abs(before.scale - 1.0) < 0.01 and before.iou > 0.95, before
    anchor = motion_anchor(before, after, rendered.lattice.centre_px)
    assert abs(anchor.range_scale - _depth(now) / _depth(then)) < 0.01, anchor
    moved = reanchor(torch.stack([then, other]), then, CENTRE, anchor, FRAME)
    assert torch.equal(moved[:, :3, :3], torch.stack([then, other])[:, :3, :3])  # attitudes untouched
    (seen,), _ = project_centre(moved[:1], ball, FRAME)
    (wanted,), _ = project_centre(now[None], ball, FRAME)
    assert (seen - wanted).abs().max() < 0.5, (seen, wanted)  # pixels
    assert abs(_depth(moved[0]) - _depth(now)) < 0.05  # 1% of the range
    assert abs(_depth(moved[1]) / _depth(other) - anchor.range_scale) < 1e-9


def test_a_model_whose_silhouette_is_too_large_still_moves_by_the_motion_alone():
    """The render's silhouette 10% larger than the detector's object (as a model trained on RGB over black
    gives): aligned with one frame alone it says the candidate is 10% too near. The motion between the two
    frames is still the camera's, and a candidate already at the right range stays at it."""
    then, now = _camera((0.0, 0.0, 6.0)), _camera((0.0, 0.0, 5.4))
    rendered = _silhouette(then, radius=1.1 * BALL)
    before, after = align(rendered, _mask(then)), align(rendered, _mask(now))
    assert abs(before.scale - 1.1) < 0.02, before  # the bias an absolute alignment would move it by
    anchor = motion_anchor(before, after, rendered.lattice.centre_px)
    assert abs(anchor.range_scale - 0.9) < 0.01, anchor
    assert np.allclose(anchor.centre_px, (FRAME.cx, FRAME.cy), atol=0.5)


def test_a_frame_that_cuts_the_object_still_measures_the_range():
    """The new frame sees the ball cut by its left edge: the overlap is measured inside the frame, where the
    whole rendered silhouette reaches, so the change of range is still found."""
    then, now = _camera((1.6, 0.0, 6.0)), _camera((1.7, 0.0, 5.4))
    mask = _mask(now)
    assert mask[:, 0].any()  # cut
    rendered = _silhouette(then)
    anchor = motion_anchor(align(rendered, _mask(then)), align(rendered, mask), rendered.lattice.centre_px)
    assert abs(anchor.range_scale - _depth(now) / _depth(then)) < 0.015, anchor
    moved = reanchor(then[None], then, CENTRE, anchor, FRAME)
    assert abs(_depth(moved[0]) - _depth(now)) < 0.08


def test_no_alignment_from_an_empty_silhouette_or_an_implausible_change_of_range():
    truth = _camera((0.0, 0.0, 5.0))
    rendered = _silhouette(truth)
    empty = np.zeros((FRAME.height, FRAME.width), bool)
    assert align(rendered, empty) is None
    assert align(Silhouette(np.zeros_like(rendered.values), rendered.lattice), _mask(truth)) is None
    assert align(rendered, _mask(_camera((0.0, 0.0, 10.0)))) is None  # half the size: not a frame's change
    same = align(rendered, _mask(truth))
    assert abs(same.scale - 1.0) < 0.005 and np.allclose(same.shift_px, 0.0, atol=0.3), same


def test_a_change_of_range_under_two_percent_is_left_out_and_the_shift_kept():
    """At a steady range a tumbling object's change of outline reads as a change of range of a percent or
    so: not applied. The camera 1% nearer and moved aside: the range stays, the image shift follows."""
    then, now = _camera((0.0, 0.0, 6.0)), _camera((0.3, 0.0, 5.94))
    rendered = _silhouette(then)
    anchor = motion_anchor(align(rendered, _mask(then)), align(rendered, _mask(now)), rendered.lattice.centre_px)
    assert anchor.range_scale == 1.0, anchor
    (wanted,), _ = project_centre(now[None], CENTRE, FRAME)
    assert abs(anchor.centre_px[0] - float(wanted[0])) < 0.5 and abs(anchor.centre_px[1] - FRAME.cy) < 0.5, anchor
