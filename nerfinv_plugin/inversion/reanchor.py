"""Re-anchoring the carried candidates on the observed silhouette before a frame's step.

The candidates a frame inherits stand where the last frame's estimate put the camera. When the range
changes from frame to frame (an approach from 9 m to 3 m closes 0.33 m, 4-10% of the range, every 5 s
frame), every candidate starts with the object too small in the image, and Adam, whose translation steps
are about a hundredth of the object's radius, spends most of a step's iterations closing that gap while
the attitude drifts with it. The observed silhouette says how far off they are: rendered at the best
carried candidate, the model's silhouette has area ``A_r`` and centroid ``c_r``, the object found in the
frame ``A_o`` and ``c_o``. Under the scaled-orthographic approximation of a small object, the range is off
by the factor ``s = sqrt(A_r / A_o)`` and, once at the new range, the projected target centre must move
so that the silhouette's centroid lands on ``c_o``: its offset from the projected centre shrinks by ``s``
too. Every carried candidate moves by that same change of range (a factor) and image position (pixels),
about its own camera axes, keeping its attitude; nothing here reads a label.

Both silhouettes are what the object detector sees: the frame's mask, and the render at the candidate
thresholded at the grey level that separated the frame's object (the model's accumulation is no substitute:
on a model trained on RGB images over black, the one the issue's user trains, its area at the true pose was
26% below the observed mask's, while the thresholded render was within 2.5% on roe1; on a tumbling roe2 it
was still 9-15% larger, which is why the option is off at a steady range). Both are read at the same
lattice of full-resolution pixel centres, at most :data:`ANCHOR_RAYS` of them, so that a frame's anchor
costs a fraction of one iteration's rays.
"""

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.initialization.detect import Detection, grey_levels
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, RenderSettings, render

ANCHOR_RAYS = 4096
"""At most this many pixels of the frame are rendered for the anchor."""
MIN_AREA_PX = 4.0
"""Less silhouette than this (full-resolution pixels, rendered or observed) gives no anchor."""
MAX_SCALE = 1.5
"""A range factor beyond ``[1 / MAX_SCALE, MAX_SCALE]`` is not applied: it says the candidate is lost or on
another part of the object, which the bank's lost check and watch deal with, not a change of range."""


@dataclass(frozen=True)
class Anchor:
    """How the carried candidates must move for the best one's silhouette to match the observed one."""

    range_scale: float
    """New range over old (``sqrt(A_r / A_o)``): below 1 the object is nearer than the candidate puts it."""
    centre_px: tuple[float, float]
    """(x, y) where the best candidate's projected target centre must go, full-resolution pixels."""


def _moments(foreground: np.ndarray, rows: np.ndarray, cols: np.ndarray, stride: int) -> tuple[float, float, float]:
    """Area (full-resolution pixels) and centroid (x, y) of ``foreground`` [h, w] bool read at the lattice of
    full-resolution pixels ``rows`` [h] x ``cols`` [w], ``stride`` apart."""
    count = int(foreground.sum())
    if count == 0:
        return 0.0, float("nan"), float("nan")
    where_rows, where_cols = np.nonzero(foreground)
    return (count * stride * stride, float((cols[where_cols] + 0.5).mean()), float((rows[where_rows] + 0.5).mean()))


def lattice(intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray, int]:
    """Rows [h] and columns [w] of the full-resolution pixels the anchor reads, ``stride`` apart (the centre
    pixel of each ``stride`` x ``stride`` block), and the stride."""
    stride = max(1, int(np.ceil(np.sqrt(intrinsics.width * intrinsics.height / ANCHOR_RAYS))))
    offset = stride // 2
    return np.arange(offset, intrinsics.height, stride), np.arange(offset, intrinsics.width, stride), stride


def project_centre(c2w: Tensor, centre: Tensor, intrinsics: Intrinsics) -> tuple[Tensor, Tensor]:
    """Pixel positions [N, 2] (x, y) of ``centre`` [3] seen from poses ``c2w`` [N, 4, 4] (nerfstudio's
    OpenGL camera axes: x right, y up, looking down -z), and its depths [N] along the optical axis."""
    rotation, position = c2w[:, :3, :3], c2w[:, :3, 3]
    local = torch.einsum("nji,nj->ni", rotation, centre[None] - position)  # R^T (C - t)
    depth = -local[:, 2]
    x = intrinsics.cx + intrinsics.fx * local[:, 0] / depth
    y = intrinsics.cy - intrinsics.fy * local[:, 1] / depth
    return torch.stack([x, y], 1), depth


def measure_anchor(rendered: np.ndarray, observed: np.ndarray, rows: np.ndarray, cols: np.ndarray, stride: int,
                   intrinsics: Intrinsics, c2w: Tensor, centre: Tensor) -> Anchor | None:
    """The :class:`Anchor` from the object as rendered at pose ``c2w`` [4, 4] and as observed, ``rendered`` and
    ``observed`` [h, w] bool on the lattice ``rows`` x ``cols`` (:func:`lattice`) of the frame of
    ``intrinsics``; None when either silhouette is (nearly) empty or the range factor is out of bounds."""
    area_r, xr, yr = _moments(rendered, rows, cols, stride)
    area_o, xo, yo = _moments(observed, rows, cols, stride)
    if min(area_r, area_o) < MIN_AREA_PX:
        return None
    scale = float(np.sqrt(area_r / area_o))
    if not 1.0 / MAX_SCALE <= scale <= MAX_SCALE:
        return None
    (pixel,), _ = project_centre(c2w[None].double(), centre.double(), intrinsics)
    px, py = float(pixel[0]), float(pixel[1])
    return Anchor(scale, (xo - (xr - px) / scale, yo - (yr - py) / scale))


def silhouette_anchor(loaded: LoadedModel, settings: RenderSettings, c2w: Tensor, detection: Detection,
                      intrinsics: Intrinsics, centre: Tensor) -> Anchor | None:
    """The anchor of the candidate ``c2w`` [4, 4] on the frame whose object is ``detection``: the
    model rendered under ``settings`` on the anchor's lattice and thresholded as the frame was (at the
    accumulation's one half when the mask came from the user, with no grey level)."""
    rows, cols, stride = lattice(intrinsics)
    grid_rows, grid_cols = np.meshgrid(rows, cols, indexing="ij")
    pixels = torch.as_tensor(np.stack([grid_rows.reshape(-1), grid_cols.reshape(-1)], 1))
    with torch.no_grad():
        out = render(loaded, c2w[None].to(torch.float32), intrinsics, pixels, settings)
    shape = (len(rows), len(cols))
    if np.isnan(detection.threshold) and out.accumulation is not None:
        rendered = out.accumulation.reshape(shape).cpu().numpy() >= 0.5
    else:
        threshold = 0.0 if np.isnan(detection.threshold) else detection.threshold
        rendered = grey_levels(out.rgb.reshape(*shape, 3).cpu().numpy()) > threshold
    observed = detection.mask[np.ix_(rows, cols)]
    return measure_anchor(rendered, observed, rows, cols, stride, intrinsics, c2w, centre)


def reanchor(c2w: Tensor, best: Tensor, centre: Tensor, anchor: Anchor, intrinsics: Intrinsics) -> Tensor:
    """Poses [N, 4, 4] (same dtype as ``c2w``) moved so that their target centre's range scales by
    ``anchor.range_scale`` and its projection shifts as the best candidate's ``best`` [4, 4] must, each
    about its own camera axes; attitudes unchanged."""
    poses = c2w.double()
    centre = centre.double()
    pixels, depth = project_centre(poses, centre, intrinsics)
    (best_px,), _ = project_centre(best[None].double(), centre, intrinsics)
    target = pixels + (torch.tensor(anchor.centre_px, dtype=torch.float64) - best_px)[None]
    new_depth = depth * anchor.range_scale
    local = torch.stack([(target[:, 0] - intrinsics.cx) / intrinsics.fx * new_depth,
                         -(target[:, 1] - intrinsics.cy) / intrinsics.fy * new_depth, -new_depth], 1)
    moved = poses.clone()
    moved[:, :3, 3] = centre[None] - torch.einsum("nij,nj->ni", poses[:, :3, :3], local)  # t = C - R p
    return moved.to(c2w.dtype)
