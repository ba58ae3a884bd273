"""Re-anchoring the carried candidates on the observed silhouettes before a frame's step.

The candidates a frame inherits stand where the last frame's estimate put the camera. When the range
changes from frame to frame (an approach from 9 m to 3 m closes 0.33 m, 4-10% of the range, every 5 s
frame), every candidate starts with the object too small in the image, and Adam, whose translation steps
are about a hundredth of the object's radius, spends most of a step's iterations closing that gap while
the attitude drifts with it; once the frame cuts the object, it no longer closes it at all
(docs/benchmarks.md). The observed silhouettes say how the camera moved.

Under the scaled-orthographic approximation of a small object, moving the camera in range by a factor ``s``
and its target centre's projection ``c`` by ``d`` pixels turns the silhouette ``R`` it sees into
``O(p) = R(c + s (p - c - d))``. :func:`align` finds the ``(s, d)`` that best map the best carried
candidate's silhouette, rendered whole (about the object's sphere, also where it leaves the frame), onto an
observed one, by the overlap of the two inside the frame (so a frame that cuts the object is measured as
well as any). It is measured twice on that one render: against the frame the candidate was estimated on and
against the new frame. Their difference is the camera's motion between the frames; every carried candidate
moves by it, in range (a factor) and image position (pixels) about its own camera axes, keeping its
attitude; a change of range under 2% is left out, as a steady range's tumbling outline reads as one. Nothing
here reads a label.

Taking the difference, not the alignment on the new frame alone, is what lets this run at a steady range:
the model's silhouette and the detector's are not the same shape (on a model trained on RGB images over
black the thresholded render was 2-15% larger in area than the frame's object at the true pose), and an
absolute alignment moved every candidate by that bias each frame (docs/benchmarks.md, session 11). Both
silhouettes are what the object detector sees: the frame's mask, and the render thresholded at the grey level
that separated that frame's object (the accumulation at one half when the mask came from the user).
"""

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nerfinv_plugin.initialization.detect import Detection, grey_levels
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, RenderSettings, render

ANCHOR_RAYS = 4096
"""At most this many rays render the candidate's silhouette."""
MAX_SCALE = 1.25
"""Range factors between ``1 / MAX_SCALE`` and ``MAX_SCALE`` are searched: more than a frame's change."""
SEARCH = ((15, 11), (9, 7), (9, 7), (9, 7))
"""(range factors, shifts along each axis) tried at each level of the coarse-to-fine search, each level
spanning two steps of the one before: about 0.25% in range and 0.15 pixels at the end."""
ALIGN_POINTS = 2048
"""At most this many pixels of a frame are compared with the rendered silhouette."""
MIN_IOU = 0.3
"""An alignment whose silhouettes overlap less than this says the candidate is lost or on another part of the
object (the bank's lost check and watch deal with that), not how the camera moved: no anchor."""
MIN_RANGE_CHANGE = 0.02
"""A measured change of range under this fraction is not applied (the image shift still is): at a steady
range the tumbling object's change of outline from frame to frame read as 0.2-1.7% of range, mostly of one
sign along a trajectory (+0.8% a frame on a toy's roe1), and applied every frame it added up faster than
Adam took it back; an approach to 3 m changed the range by 2-13% a frame (docs/benchmarks.md)."""
MIN_AREA_PX = 4.0
"""Less silhouette than this (full-resolution pixels, rendered or observed) gives no anchor."""


@dataclass(frozen=True)
class Anchor:
    """How the carried candidates must move for the best one to follow the camera's motion."""

    range_scale: float
    """New range over old: below 1 the object is nearer than the candidate puts it."""
    centre_px: tuple[float, float]
    """(x, y) where the best candidate's projected target centre must go, full-resolution pixels."""


@dataclass(frozen=True)
class Lattice:
    """Full-resolution pixel centres ``(x0 + j stride, y0 + i stride)`` about a candidate's projected object,
    reaching beyond the frame where the object does."""

    x0: float
    y0: float
    stride: int
    shape: tuple[int, int]
    """(h, w)."""
    centre_px: tuple[float, float]
    """Where the target centre projects (x, y)."""
    radius_px: float
    """The object's sphere's radius in the image: the silhouette lies within it of ``centre_px``."""


@dataclass(frozen=True)
class Silhouette:
    """A candidate's rendered silhouette on its :class:`Lattice`."""

    values: np.ndarray
    """[h, w] float32, 1 on the object and 0 off it."""
    lattice: Lattice


@dataclass(frozen=True)
class Rendered:
    """A candidate rendered on its lattice, forward only: what its silhouette is thresholded from."""

    rgb: np.ndarray
    """[h, w, 3] in [0, 1]."""
    accumulation: np.ndarray | None
    """[h, w], where the model has it."""
    lattice: Lattice

    def silhouette(self, detection: Detection) -> Silhouette:
        """The render as the detector saw the frame of ``detection``: its grey levels above that frame's
        threshold (the accumulation at one half when the mask came from the user, with no grey level)."""
        if np.isnan(detection.threshold) and self.accumulation is not None:
            values = self.accumulation >= 0.5
        else:
            values = grey_levels(self.rgb) > (0.0 if np.isnan(detection.threshold) else detection.threshold)
        return Silhouette(values.astype(np.float32), self.lattice)


@dataclass(frozen=True)
class Alignment:
    """``(s, d)`` of ``O(p) = R(c + s (p - c - d))`` for a rendered silhouette ``R`` and an observed ``O``."""

    scale: float
    shift_px: tuple[float, float]
    iou: float


def project_centre(c2w: Tensor, centre: Tensor, intrinsics: Intrinsics) -> tuple[Tensor, Tensor]:
    """Pixel positions [N, 2] (x, y) of ``centre`` [3] seen from poses ``c2w`` [N, 4, 4] (nerfstudio's
    OpenGL camera axes: x right, y up, looking down -z), and its depths [N] along the optical axis."""
    rotation, position = c2w[:, :3, :3], c2w[:, :3, 3]
    local = torch.einsum("nji,nj->ni", rotation, centre[None] - position)  # R^T (C - t)
    depth = -local[:, 2]
    x = intrinsics.cx + intrinsics.fx * local[:, 0] / depth
    y = intrinsics.cy - intrinsics.fy * local[:, 1] / depth
    return torch.stack([x, y], 1), depth


def _stride(width: float, height: float, count: int = ANCHOR_RAYS) -> int:
    """The smallest lattice spacing (full-resolution pixels) that covers ``width`` x ``height`` with at most
    ``count`` points."""
    return max(1, int(np.ceil(np.sqrt(max(width, 1.0) * max(height, 1.0) / count))))


def lattice_about(c2w: Tensor, centre: Tensor, radius: float, intrinsics: Intrinsics) -> Lattice:
    """The lattice a candidate ``c2w`` [4, 4] is rendered on: the box of its image of the object's sphere of
    ``radius`` about ``centre`` (model units), at most :data:`ANCHOR_RAYS` points."""
    (pixel,), depth = project_centre(c2w[None].double(), centre.double(), intrinsics)
    distance = max(float(depth[0]), 1.001 * radius)
    radius_px = float(max(intrinsics.fx, intrinsics.fy) * radius / np.sqrt(distance ** 2 - radius ** 2))
    radius_px = min(radius_px, 2.0 * max(intrinsics.width, intrinsics.height))  # a camera inside the sphere
    stride = _stride(2.0 * radius_px, 2.0 * radius_px)
    x, y = float(pixel[0]), float(pixel[1])
    left, top = np.floor(x - radius_px - 0.5), np.floor(y - radius_px - 0.5)
    shape = (int((np.ceil(y + radius_px) - top) // stride) + 1, int((np.ceil(x + radius_px) - left) // stride) + 1)
    return Lattice(float(left) + 0.5, float(top) + 0.5, stride, shape, (x, y), radius_px)


def render_on_lattice(loaded: LoadedModel, settings: RenderSettings, c2w: Tensor, lattice: Lattice,
                      intrinsics: Intrinsics) -> Rendered:
    """The candidate ``c2w`` [4, 4] rendered under ``settings`` at the pixels of ``lattice``, through a camera
    that extends the frame's (same focal lengths, the principal point moved) so that pixels beyond the frame
    are rays like any other."""
    h, w = lattice.shape
    rows = (lattice.y0 - 0.5 + lattice.stride * np.arange(h)).astype(np.int64)
    cols = (lattice.x0 - 0.5 + lattice.stride * np.arange(w)).astype(np.int64)
    ox, oy = int(-min(cols[0], 0)), int(-min(rows[0], 0))
    wide = Intrinsics(intrinsics.fx, intrinsics.fy, intrinsics.cx + ox, intrinsics.cy + oy,
                      int(max(cols[-1] + 1, intrinsics.width) + ox), int(max(rows[-1] + 1, intrinsics.height) + oy))
    grid_rows, grid_cols = np.meshgrid(rows + oy, cols + ox, indexing="ij")
    pixels = torch.as_tensor(np.stack([grid_rows.reshape(-1), grid_cols.reshape(-1)], 1))
    with torch.no_grad():
        out = render(loaded, c2w[None].to(torch.float32), wide, pixels, settings)
    return Rendered(out.rgb.reshape(h, w, 3).cpu().numpy(),
                    None if out.accumulation is None else out.accumulation.reshape(h, w).cpu().numpy(), lattice)


def _observed_points(silhouette: Silhouette, mask: np.ndarray, reach_px: float) -> Tensor:
    """Pixel centres (x, y) [P, 2] of a lattice over the frame's part where either silhouette can be (the
    mask's box and the rendered sphere's, widened by ``reach_px``)."""
    height, width = mask.shape
    ys, xs = np.nonzero(mask)
    (cx, cy), r = silhouette.lattice.centre_px, silhouette.lattice.radius_px
    left = int(max(0, np.floor(min(xs.min(), cx - r) - reach_px)))
    right = int(min(width, np.ceil(max(xs.max() + 1, cx + r) + reach_px)))
    top = int(max(0, np.floor(min(ys.min(), cy - r) - reach_px)))
    bottom = int(min(height, np.ceil(max(ys.max() + 1, cy + r) + reach_px)))
    stride = _stride(right - left, bottom - top, ALIGN_POINTS)
    grid_rows, grid_cols = np.meshgrid(np.arange(top, bottom, stride), np.arange(left, right, stride), indexing="ij")
    return torch.as_tensor(np.stack([grid_cols.reshape(-1) + 0.5, grid_rows.reshape(-1) + 0.5], 1),
                           dtype=torch.float32)


def _overlaps(smooth: Silhouette, points: Tensor, observed: Tensor, scales: Tensor, shifts: Tensor) -> Tensor:
    """The soft IoU ``sum min / sum max`` [S, D] of the smoothed observed mask at ``points`` [P] with the
    smoothed silhouette mapped by every scale [S] and shift [D, 2]: read bilinearly (zero beyond its lattice)
    at ``c + s (p - c - d)``. Where the two smoothed silhouettes agree it is exactly 1, wherever the points
    fall, so its peak is where the silhouettes agree."""
    lattice = smooth.lattice
    values = torch.as_tensor(smooth.values)[None, None]
    h, w = smooth.values.shape
    c = torch.tensor(lattice.centre_px, dtype=torch.float32)
    span = torch.tensor([max(w - 1, 1), max(h - 1, 1)], dtype=torch.float32) * lattice.stride
    origin = torch.tensor([lattice.x0, lattice.y0], dtype=torch.float32)
    to_grid = 2.0 / span  # lattice pixels to grid_sample's [-1, 1]
    total = observed.sum()
    ious = []
    for scale in scales:  # one scale at a time: [D, P, 2] stays small; the warp is affine in the points
        offsets = (c * (1.0 - scale) - scale * shifts - origin) * to_grid - 1.0
        grid = (points * (scale * to_grid))[None] + offsets[:, None, :]
        sampled = F.grid_sample(values, grid[None], mode="bilinear", padding_mode="zeros", align_corners=True)[0, 0]
        common = torch.minimum(sampled, observed).sum(-1)
        ious.append(common / (sampled.sum(-1) + total - common).clamp_min(1e-6))  # sum max = sum a + sum b - sum min
    return torch.stack(ious)


def align(silhouette: Silhouette, mask: np.ndarray) -> Alignment | None:
    """The range factor and image shift that best map ``silhouette`` onto the observed ``mask`` [H, W] bool
    (:class:`Alignment`), searched coarse to fine (:data:`SEARCH`): range factors within :data:`MAX_SCALE`,
    shifts within half the object's image radius (at least 8 pixels). None when either silhouette is (nearly)
    empty, when they overlap less than :data:`MIN_IOU` at best, or when the best factor is at the search's end.

    Both silhouettes are smoothed first, by a Gaussian one lattice stride wide (the frame's beyond its border
    continued from its edge): compared as hard masks, the best overlap came where the lattice's points fell on
    pixel centres, not where the silhouettes agree (range factors pulled to exactly 1 by 1% on a 30-pixel
    disc, shifts a stride off)."""
    stride = silhouette.lattice.stride
    if mask.sum() < MIN_AREA_PX or silhouette.values.sum() * stride ** 2 < MIN_AREA_PX:
        return None
    smooth = Silhouette(cv2.GaussianBlur(silhouette.values, (0, 0), 1.0, borderType=cv2.BORDER_CONSTANT),
                        silhouette.lattice)
    reach = max(8.0, silhouette.lattice.radius_px / 2.0)
    points = _observed_points(silhouette, mask, reach)
    blurred = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), float(stride), borderType=cv2.BORDER_REPLICATE)
    rows, cols = (points[:, 1] - 0.5).long().numpy(), (points[:, 0] - 0.5).long().numpy()
    observed = torch.as_tensor(blurred[rows, cols])
    log_scale, shift = 0.0, torch.zeros(2)
    log_half, shift_half = float(np.log(MAX_SCALE)), reach
    best = 0.0
    for scale_count, shift_count in SEARCH:
        log_scales = torch.linspace(log_scale - log_half, log_scale + log_half, scale_count)
        offsets = torch.linspace(-shift_half, shift_half, shift_count)
        shifts = shift + torch.stack(torch.meshgrid(offsets, offsets, indexing="xy"), -1).reshape(-1, 2)
        iou = _overlaps(smooth, points, observed, torch.exp(log_scales), shifts)
        i, j = divmod(int(torch.argmax(iou)), iou.shape[1])
        log_scale, shift, best = float(log_scales[i]), shifts[j].clone(), float(iou[i, j])
        log_half, shift_half = 2.0 * log_half / (scale_count - 1), 2.0 * shift_half / (shift_count - 1)
    if best < MIN_IOU or abs(log_scale) >= np.log(MAX_SCALE):  # at the search's end: the change is larger
        return None
    return Alignment(float(np.exp(log_scale)), (float(shift[0]), float(shift[1])), best)


def motion_anchor(before: Alignment, after: Alignment, centre_px: tuple[float, float]) -> Anchor:
    """The camera's motion between two frames, from one candidate's silhouette aligned with each: on the frame
    it was estimated on (``before``) and on the next (``after``); ``centre_px`` is its projected target centre.

    The warps ``W(p) = c + (p - c) / s + d`` take the render to each observed silhouette; the motion is
    ``W_after`` after the inverse of ``W_before``: a range factor ``s_after / s_before``, and the projected
    centre moves to ``c + d_after - d_before s_before / s_after``. A change of range under
    :data:`MIN_RANGE_CHANGE` is left out (the range factor 1), the shift kept."""
    ratio = before.scale / after.scale
    x = centre_px[0] + after.shift_px[0] - before.shift_px[0] * ratio
    y = centre_px[1] + after.shift_px[1] - before.shift_px[1] * ratio
    range_scale = after.scale / before.scale
    return Anchor(range_scale if abs(np.log(range_scale)) >= MIN_RANGE_CHANGE else 1.0, (x, y))


def silhouette_anchor(loaded: LoadedModel, settings: RenderSettings, c2w: Tensor, before: Detection,
                      after: Detection, intrinsics: Intrinsics, centre: Tensor, radius: float) -> Anchor | None:
    """The anchor of the candidate ``c2w`` [4, 4], estimated on the frame whose object is ``before``, for
    the frame whose object is ``after``; the object lies within ``radius`` (model units) of ``centre``.
    One render of its silhouette, aligned with both; None when either alignment fails."""
    lattice = lattice_about(c2w, centre, radius, intrinsics)
    rendered = render_on_lattice(loaded, settings, c2w, lattice, intrinsics)
    then, now = align(rendered.silhouette(before), before.mask), align(rendered.silhouette(after), after.mask)
    if then is None or now is None:
        return None
    return motion_anchor(then, now, lattice.centre_px)


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
