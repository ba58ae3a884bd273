"""A view bank of the loaded model, and matching an observed frame against it: pose hypotheses from
nothing but the model and the image.

The bank renders the model from viewpoints over the whole sphere (an icosphere) at a nominal range, with
the object's centre on the optical axis, forward only, and keeps small images of colour and accumulation.
Every view is then turned through in-plane angles (rolling a camera about its axis turns its image about
the principal point, exactly), the object's box is found in each turned image with the same detector that
reads the observed frames, and a square crop about the box becomes one entry. Matching crops the observed
frame the same way and scores every entry at once (two matrix products): silhouette overlap plus
zero-mean correlation of grey levels. The best entries, kept apart on SO(3) so that distinct modes such as
a half-turn flip survive, become full poses through their boxes (:mod:`box_pose`).

Rendering is the expensive part, so the renders are cached on disk, keyed on the checkpoint's bytes and
everything else that determines them. The entries computed from them are cached beside them (3.6 s to
compute for the default bank on the 2-core machine, a few tenths of a second to read; about 190 MB),
keyed on the bank, the entry settings and the source of the code that computes them (this module and the
detector), so that a changed detector never meets entries cut by the old one.
"""

import hashlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.geometry.frames import OPENCV_TO_OPENGL, look_at_c2w_opencv, rotmat_to_quat_wxyz
from nerfinv_plugin.initialization.box_pose import BankView, pose_from_box
from nerfinv_plugin.initialization.detect import Detection, find_object
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, RenderSettings, render, sample_counts

BANK_FORMAT = 1
"""Bumped whenever what a cached bank holds changes, so old caches are rebuilt."""
CROP_MARGIN = 1.2
"""Crops are squares of this many times the box's larger side (the Augmented Autoencoder's 1.2)."""


@dataclass(frozen=True)
class BankConfig:
    """The view bank that starting poses are drawn from when nothing is known of the pose."""

    subdivisions: int = 3
    """Icosphere subdivisions of the viewpoints: 2, 3, 4 give 162, 642, 2562 views (about 17, 8, 4 degrees
    apart)."""
    in_plane: int = 36
    """In-plane angles per view (36: every 10 degrees)."""
    render_px: int = 48
    """Side of each rendered view (pixels); the object's bounding sphere fills 90% of it."""
    crop_px: int = 32
    """Side of the crops that are compared (pixels)."""
    range_radii: float = 6.0
    """Nominal range of the bank cameras, in object radii (the object's apparent size is matched through
    the box, so this only sets the perspective)."""
    silhouette_weight: float = 0.5
    """Score = this x silhouette IoU + the rest x zero-mean correlation of grey levels."""
    nms_deg: float = 10.0
    """Hypotheses closer than this on SO(3) to a better one are dropped (keeps distinct modes)."""
    batch_views: int = 16
    """Views rendered in one batch."""

    @property
    def views(self) -> int:
        return 10 * 4**self.subdivisions + 2


def icosphere(subdivisions: int) -> np.ndarray:
    """Unit vectors [10 * 4^n + 2, 3]: the vertices of an icosahedron whose faces were split ``n`` times."""
    t = (1.0 + 5.0**0.5) / 2.0
    vertices = [np.array(v, dtype=np.float64) for v in
                [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
                 (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
             (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    midpoint: dict[tuple[int, int], int] = {}  # an edge's midpoint is shared by the two faces on it

    def middle(a: int, b: int) -> int:
        key = (min(a, b), max(a, b))
        if key not in midpoint:
            vertices.append((vertices[a] + vertices[b]) / 2.0)
            midpoint[key] = len(vertices) - 1
        return midpoint[key]

    for _ in range(subdivisions):
        midpoint.clear()
        split = []
        for a, b, c in faces:
            ab, bc, ca = middle(a, b), middle(b, c), middle(c, a)
            split += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = split
    points = np.array(vertices)
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def _save_npz(path: Path, writer: Callable[..., None], **arrays: np.ndarray) -> None:
    """``writer`` (``np.savez`` or ``np.savez_compressed``) to a name of this process beside ``path``, then moved
    into place: two runs caching the same file at once (grid workers) never leave half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial.npz")
    writer(partial, **arrays)
    os.replace(partial, path)


@dataclass
class ViewBank:
    """The rendered views (model frame) and what they were rendered with."""

    c2w: np.ndarray
    """[V, 4, 4] camera-to-world, OpenGL axes, model frame: at ``range`` from ``centre``, looking at it."""
    rgb: np.ndarray
    """[V, S, S, 3] uint8 renders over black."""
    accumulation: np.ndarray
    """[V, S, S] uint8 (opacity x 255)."""
    centre: np.ndarray
    """[3] object centre, model frame."""
    radius: float
    """Object radius, model units."""
    range: float
    """Camera distance from the centre, model units."""
    focal: float
    """Focal length of the renders, pixels (principal point at the image centre)."""
    build_s: float = 0.0
    """Seconds the renders took when the bank was built (kept in the cache file, so a bank read from the
    cache reports the time it once took)."""

    def save(self, path: Path) -> None:
        _save_npz(path, np.savez_compressed, c2w=self.c2w, rgb=self.rgb, accumulation=self.accumulation,
                  centre=self.centre, scalars=np.array([self.radius, self.range, self.focal, self.build_s]))

    @classmethod
    def load(cls, path: Path) -> "ViewBank":
        with np.load(path) as data:
            radius, range_, focal, build_s = (float(v) for v in data["scalars"])
            return cls(data["c2w"], data["rgb"], data["accumulation"], data["centre"], radius, range_, focal, build_s)


def bank_intrinsics(config: BankConfig) -> Intrinsics:
    """The square pinhole camera of the renders: the object's bounding sphere, seen from
    ``config.range_radii`` radii away, fills 90% of it."""
    half_angle = np.arcsin(1.0 / config.range_radii)
    focal = 0.5 * config.render_px * 0.9 / np.tan(half_angle)
    side = config.render_px
    return Intrinsics(focal, focal, side / 2, side / 2, side, side)


def render_bank(loaded: LoadedModel, settings: RenderSettings, centre: np.ndarray, radius: float,
                config: BankConfig, advance: Callable[[int], None] = lambda views: None) -> ViewBank:
    """Render every viewpoint under ``settings`` (forward only, in batches); ``advance(n)`` after each batch
    of ``n`` views."""
    tic = time.perf_counter()
    intrinsics = bank_intrinsics(config)
    distance = config.range_radii * radius
    eyes = np.asarray(centre, dtype=np.float64) + distance * icosphere(config.subdivisions)
    c2w = np.array([look_at_c2w_opencv(eye, centre) @ OPENCV_TO_OPENGL for eye in eyes])
    side = config.render_px
    rows, cols = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    pixels = torch.stack([rows.reshape(-1), cols.reshape(-1)], 1)
    rgb, accumulation = [], []
    with torch.no_grad():
        for start in range(0, len(c2w), config.batch_views):
            batch = torch.as_tensor(c2w[start:start + config.batch_views], dtype=torch.float32)
            out = render(loaded, batch, intrinsics, pixels, settings)
            rgb.append((out.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).reshape(-1, side, side, 3).cpu().numpy())
            acc = out.accumulation if out.accumulation is not None else out.rgb.amax(-1, keepdim=True)
            accumulation.append((acc.clamp(0, 1) * 255 + 0.5).to(torch.uint8).reshape(-1, side, side).cpu().numpy())
            advance(len(batch))
    return ViewBank(c2w, np.concatenate(rgb), np.concatenate(accumulation), np.asarray(centre, dtype=np.float64),
                    float(radius), float(distance), float(intrinsics.fx), time.perf_counter() - tic)


def cache_root() -> Path:
    return Path(os.environ.get("NERFINV_CACHE", Path.home() / ".cache" / "nerfinv")) / "banks"


def file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def bank_key(loaded: LoadedModel, settings: RenderSettings, centre: np.ndarray, radius: float,
             config: BankConfig) -> str:
    """What determines the renders: the checkpoint's bytes, the sample counts ``settings`` give, the rays'
    bound, the viewpoints and the render size."""
    counts = sample_counts(loaded, settings)
    samples = None if counts is None else [list(counts[0]), counts[1]]
    sphere = settings.target_sphere
    bound = None if sphere is None else [np.round(sphere[0].cpu().numpy().astype(np.float64), 6).tolist(),
                                         round(float(sphere[1]), 6)]
    settings = {"format": BANK_FORMAT, "checkpoint": file_digest(loaded.checkpoint), "samples": samples,
                "bound": bound, "centre": np.round(np.asarray(centre, dtype=np.float64), 6).tolist(),
                "radius": round(float(radius), 6), "subdivisions": config.subdivisions,
                "render_px": config.render_px, "range_radii": config.range_radii}
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:20]


def bank_file(loaded: LoadedModel, settings: RenderSettings, centre: np.ndarray, radius: float,
              config: BankConfig) -> Path:
    """Where the bank of these settings is cached."""
    return cache_root() / f"bank-{bank_key(loaded, settings, centre, radius, config)}.npz"


def cached_bank(loaded: LoadedModel, settings: RenderSettings, centre: np.ndarray, radius: float, config: BankConfig,
                on_build: Callable[[int], Callable[[int], None]] | None = None) -> tuple[ViewBank, Path, bool]:
    """The bank from the cache, or rendered and cached; ``(bank, cache file, was it built)``.
    ``on_build(total_views)`` is called before rendering and returns the per-batch ``advance``."""
    path = bank_file(loaded, settings, centre, radius, config)
    if path.is_file():
        try:
            return ViewBank.load(path), path, False
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is rebuilt
    advance = on_build(config.views) if on_build is not None else (lambda views: None)
    bank = render_bank(loaded, settings, centre, radius, config, advance)
    bank.save(path)
    return bank, path, True


def crop_affine(angle: float, centre: tuple[float, float], side: float, out_px: int,
                pivot: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The 2x3 matrix (cv2 pixel-index coordinates) that turns an image by ``angle`` (radians, x right,
    y down) about ``pivot`` and then maps the square of ``side`` pixels about ``centre`` (continuous
    coordinates, in the turned image) onto ``out_px`` x ``out_px`` pixels."""
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s], [s, c]])
    scale = out_px / side
    # continuous coordinates x = index + 0.5 on both sides
    shift = -turn @ np.asarray(pivot) + np.asarray(pivot) - np.asarray(centre) + side / 2.0
    matrix = np.zeros((2, 3))
    matrix[:, :2] = scale * turn
    matrix[:, 2] = scale * (turn @ np.array([0.5, 0.5]) + shift) - 0.5
    return matrix


def crop(image: np.ndarray, matrix: np.ndarray, side: float, out_px: int) -> np.ndarray:
    """``image`` (float32, [H, W] or [H, W, C]) through ``matrix`` (from :func:`crop_affine`), zero outside,
    smoothed first in proportion to the shrink so that small crops of large objects do not alias."""
    shrink = side / out_px
    if shrink > 1.0:
        image = cv2.GaussianBlur(image, (0, 0), 0.5 * np.sqrt(shrink**2 - 1.0))
    return cv2.warpAffine(image, matrix, (out_px, out_px), flags=cv2.INTER_LINEAR, borderValue=0.0)


def grey(rgb: np.ndarray) -> np.ndarray:
    """Mean of the channels, in [0, 1]."""
    return rgb.astype(np.float32).mean(-1) / 255.0


def _normalised(values: np.ndarray) -> np.ndarray:
    """Rows made zero-mean and unit-norm (rows that are constant stay zero)."""
    centred = values - values.mean(-1, keepdims=True)
    norm = np.linalg.norm(centred, axis=-1, keepdims=True)
    return centred / np.maximum(norm, 1e-8)


@dataclass
class Features:
    """One crop as the matcher compares it: the silhouette and the normalised grey levels, flattened."""

    mask: np.ndarray
    grey: np.ndarray


def crop_features(image: np.ndarray, detection: Detection, out_px: int) -> Features:
    """The features of the crop about ``detection``'s box in ``image`` (RGB uint8)."""
    side = CROP_MARGIN * detection.size
    matrix = crop_affine(0.0, detection.centre, side, out_px)
    both = crop(np.dstack([detection.mask.astype(np.float32), grey(image)]), matrix, side, out_px)
    return Features(both[..., 0].reshape(-1), _normalised(both[..., 1].reshape(1, -1))[0])


def turned_boxes(mask: np.ndarray, angles: np.ndarray, pivot: tuple[float, float]) -> np.ndarray:
    """Boxes [A, 4] (x0, y0, x1, y1, continuous coordinates) of ``mask`` turned by each angle about
    ``pivot``: the extremes of its turned pixel centres, half a pixel out (exact at angle 0)."""
    rows, cols = np.nonzero(mask)
    points = np.stack([cols + 0.5, rows + 0.5], 1) - np.asarray(pivot)
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    x = c * points[:, 0] - s * points[:, 1] + pivot[0]
    y = s * points[:, 0] + c * points[:, 1] + pivot[1]
    return np.stack([x.min(1) - 0.5, y.min(1) - 0.5, x.max(1) + 0.5, y.max(1) + 0.5], 1)


def _rolled(w2c: np.ndarray, angle: float) -> np.ndarray:
    """World-to-camera rotation of a camera rolled so that its image turns by ``angle`` (radians, x right,
    y down): image points are camera x, y over z, so the image turns with the camera frame's x-y plane."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ w2c


@dataclass
class BankEntries:
    """Every (view, in-plane angle) of a bank as the matcher uses it."""

    masks: np.ndarray
    """[E, crop_px^2] silhouettes."""
    greys: np.ndarray
    """[E, crop_px^2] zero-mean, unit-norm grey levels."""
    views: list[BankView]
    """Per entry: the rolled camera and its box."""
    quaternions: np.ndarray
    """[E, 4] the entries' world-to-camera rotations, for suppression on SO(3)."""

    def save(self, path: Path) -> None:
        """Uncompressed: reading is what a run waits for."""
        views = self.views
        _save_npz(path, np.savez, masks=self.masks, greys=self.greys, quaternions=self.quaternions,
                  rotations=np.array([v.w2c_rotation for v in views]).reshape(-1, 3, 3),
                  offsets=np.array([v.box_offset for v in views], dtype=np.float64).reshape(-1, 2),
                  sizes=np.array([v.box_size for v in views], dtype=np.float64),
                  cameras=np.array([[v.range, v.focal] for v in views], dtype=np.float64).reshape(-1, 2))

    @classmethod
    def load(cls, path: Path) -> "BankEntries":
        with np.load(path) as data:
            views = [BankView(rotation, float(camera[0]), float(camera[1]), (float(offset[0]), float(offset[1])),
                              float(size))
                     for rotation, camera, offset, size in zip(data["rotations"], data["cameras"], data["offsets"],
                                                               data["sizes"])]
            return cls(data["masks"], data["greys"], views, data["quaternions"])


def bank_entries(bank: ViewBank, config: BankConfig) -> BankEntries:
    """Turn every view through the in-plane angles, box the object in each turned image and crop it as an
    observed frame is cropped (one affine warp per entry). Views in which the detector finds nothing are
    left out."""
    side = bank.rgb.shape[1]
    pivot = (side / 2.0, side / 2.0)  # the principal point: turning about it is rolling the camera
    angles = 2.0 * np.pi * np.arange(config.in_plane) / config.in_plane
    masks, greys, views, rotations = [], [], [], []
    for index in range(len(bank.rgb)):
        found = find_object(bank.rgb[index])
        if found is None:
            continue
        w2c = (bank.c2w[index] @ OPENCV_TO_OPENGL)[:3, :3].T
        stack = np.dstack([found.mask.astype(np.float32), grey(bank.rgb[index])])
        for angle, box in zip(angles, turned_boxes(found.mask, angles, pivot)):
            centre = ((box[0] + box[2]) / 2.0, (box[1] + box[3]) / 2.0)
            size = float(max(box[2] - box[0], box[3] - box[1]))
            crop_side = CROP_MARGIN * size
            both = crop(stack, crop_affine(angle, centre, crop_side, config.crop_px, pivot), crop_side, config.crop_px)
            masks.append(both[..., 0].reshape(-1))
            greys.append(both[..., 1].reshape(-1))
            rotation = _rolled(w2c, angle)
            views.append(BankView(rotation, bank.range, bank.focal, (centre[0] - pivot[0], centre[1] - pivot[1]), size))
            rotations.append(rotation)
    # One batched conversion: one call per entry took most of the time it takes to read a cached bank.
    quaternions = rotmat_to_quat_wxyz(np.array(rotations).reshape(-1, 3, 3))
    return BankEntries(np.array(masks, dtype=np.float32), _normalised(np.array(greys, dtype=np.float32)), views,
                       quaternions)


def entries_file(bank_path: Path, config: BankConfig) -> Path:
    """Where the entries of the bank cached at ``bank_path`` are cached: keyed on it, on the entry settings,
    and on the bytes of the code that cuts them (this module, the detector)."""
    digest = hashlib.sha256(f"{bank_path.name} {config.in_plane} {config.crop_px} {CROP_MARGIN}".encode())
    for source in (Path(__file__), Path(find_object.__code__.co_filename)):
        digest.update(source.read_bytes())
    return bank_path.with_name(f"entries-{digest.hexdigest()[:20]}.npz")


def cached_entries(bank: ViewBank, bank_path: Path, config: BankConfig) -> BankEntries:
    """:func:`bank_entries` of ``bank`` (cached at ``bank_path``), from the cache or computed and cached."""
    path = entries_file(bank_path, config)
    if path.is_file():
        try:
            return BankEntries.load(path)
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is computed again
    entries = bank_entries(bank, config)
    if entries.views:
        entries.save(path)
    return entries


@dataclass(frozen=True)
class Hypothesis:
    """A pose the bank proposes for an observed frame."""

    c2w: np.ndarray
    """[4, 4] camera-to-world, OpenGL axes, model frame."""
    score: float
    entry: int


def scores(entries: BankEntries, observed: Features, silhouette_weight: float) -> np.ndarray:
    """Score of every entry [E]: silhouette IoU (soft) and grey-level correlation, weighted."""
    inter = entries.masks @ observed.mask
    union = entries.masks.sum(1) + observed.mask.sum() - inter
    iou = inter / np.maximum(union, 1e-6)
    return silhouette_weight * iou + (1.0 - silhouette_weight) * (entries.greys @ observed.grey)


def hypotheses(entries: BankEntries, image: np.ndarray, detection: Detection, intrinsics: Intrinsics,
               centre: np.ndarray, count: int, config: BankConfig) -> list[Hypothesis]:
    """The ``count`` best-scoring poses for the object ``detection`` found in ``image``, at least
    ``config.nms_deg`` apart on SO(3), best first."""
    observed = crop_features(image, detection, config.crop_px)
    ranked = scores(entries, observed, config.silhouette_weight)
    order = np.argsort(-ranked)
    threshold = np.cos(np.radians(config.nms_deg) / 2.0)
    kept: list[int] = []
    for index in order:
        if kept and (np.abs(entries.quaternions[kept] @ entries.quaternions[index]) > threshold).any():
            continue
        kept.append(int(index))
        if len(kept) == count:
            break
    out = []
    for index in kept:
        c2w_cv = pose_from_box(entries.views[index], detection.centre, detection.size, intrinsics.fx, intrinsics.fy,
                               intrinsics.cx, intrinsics.cy, centre)
        out.append(Hypothesis(c2w_cv @ OPENCV_TO_OPENGL, float(ranked[index]), index))
    return out


def hypothesis_poses(found: list[Hypothesis]) -> Tensor:
    """[K, 4, 4] float32 model-frame poses of hypotheses, for the tracker."""
    return torch.as_tensor(np.array([h.c2w for h in found]), dtype=torch.float32)
