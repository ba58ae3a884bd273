"""The object in an observed frame: its foreground mask, box and centroid, from the image alone.

A view bank is matched against the crop around the object and the translation is set from its box, so the
box must hold the whole object (thin antennas, a panel behind a dark gap) and nothing else (sensor noise,
hot pixels, stars). Frames are RGB ``uint8`` [H, W, 3] of a lit object on a dark background, at low
resolution (240 x 150, sometimes 120 x 75). :func:`find_object` works in these steps, each for a reason:

1. **Grey = max over channels.** A thin part in one strong colour (a blue panel edge-on, a gold antenna)
   stays as bright as its brightest channel; a luminance average would dim it by up to two thirds.
2. **Background level and noise from the dark side** (:func:`estimate_background`): the frame is mostly
   background, so start from its darkest quarter and grow a 3-sigma clipped sample until it stops
   changing. The level is that sample's median; the noise is measured on its *bright* side only
   (1.4826 x median of the deviations above the level), because the bright tail is what the threshold must
   clear, and on a black frame the dark side is clipped at 0 and says nothing.
   **A noisy frame is smoothed first** (:func:`pixel_noise`): when the noise between neighbouring pixels
   is above 5 grey levels, a 3 x 3 median filter runs on the grey image before steps 2-6. A lab camera's
   frame (the lightbox-like domain of ``ns-invert-synth``: read and shot noise under display gamma 2,
   clipped at 0, then JPEG) has a lifted background (level 15) whose noise, on the max over channels (10
   levels), puts the threshold at 67 and cuts all but the brightest faces. Filtered, the noise is 4.4 and
   the threshold 37. On 40 such frames of the spacecraft (240 x 150) the mask's IoU with the object's alpha
   went from a median of 0.52 (0 on two frames: the object lost) to 0.58 (at least 0.08); the same views
   rendered without the lab camera score 0.55 (the lab lamp leaves faces black). A median, not a blur,
   because it keeps the outline in place (a Gaussian of sigma 1 px widened it: IoU 0.87 against 0.91 on
   the well-lit frames). Per-channel Gaussian noise of sigma 3 measures 2.1 here, sigma 6 4.2, sigma 10
   6.3 (smoothed as well), a lab frame 7-8.5, a noise-free render 0.
3. **Threshold = level + clamp(5 x noise, 12, 64) grey levels.** Five noise units leave about one
   background pixel in a 240 x 150 frame above it (measured for Gaussian noise of 0-10 grey levels, per
   channel or shared, on black or grey backgrounds). The floor of 12 is for noise-free frames (renders of
   the model), whose noise estimate is 0: it keeps their soft fringe and faint floaters out, while a body's
   anti-aliased edge still lands within a pixel. The cap keeps a frame the object fills (where the
   estimate can run into the object) from losing the object entirely. No Otsu split: it would cut the
   object's shadowed side, which a spacecraft under one sun always has.
4. **A 3 x 3 closing** fills the pinholes noise leaves in a dim, shadowed part (the mask is matched
   against the view bank, so it should be whole) and rejoins a thin part broken by 1-px gaps. A closing
   never reaches outside the box of what it closes, so it cannot grow the box.
5. **Components (8-connected, so diagonal antennas hold together): keep the largest, every other one at
   least a fifth of its area, and then, repeatedly, any component within ``max(4 px, 10 % of the largest
   one's size)`` of what is kept.** The largest is the object's body; a big second piece is the object
   too (a panel on an unlit boom); a small piece close by is a detached antenna or a panel behind a dark
   gap. Isolated specks, hot pixels and stars far away are dropped.
6. **None** when the largest component is below ``min_area`` pixels: an empty, black or noise-only frame.

What it does not remove, measured on the tests' drawn spacecraft: JPEG at quality 60-90 adds 2-3 px on the
side of a saturated colour edge (ringing and chroma bleed at 10-15 % of the edge's contrast, once JPEG has
smoothed the noise the threshold is set from); a bloom halo is object as far as it is above the threshold
(a halo adding 0.2 to 0.8 x the image blurred with sigma 4 px: +2 to +6 px); a hot pixel or star within
the near distance joins the object. A smooth glow over the whole frame raises the noise estimate instead.

Masks can also come from the user (:func:`read_masks`, :func:`detection_from_mask`).

Pixel conventions: pixel (row i, col j) covers [j, j + 1) x [i, i + 1); boxes use these continuous
coordinates with exclusive right and bottom edges; centroids are means of pixel centres (j + 0.5, i + 0.5).
"""

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

NOISE_UNITS = 5.0
"""Threshold above the background level, in noise units (step 3)."""
MIN_CONTRAST = 12.0
"""Smallest threshold above the background level, grey levels (step 3)."""
MAX_CONTRAST = 64.0
"""Largest threshold above the background level, grey levels (step 3)."""
CLIP_UNITS = 3.0
"""Width of the clipped background sample, in noise units (step 2)."""
LARGE_FRACTION = 0.2
"""A component this fraction of the largest one's area is kept wherever it is (step 5)."""
NEAR_MIN_PX = 4
"""A component with at most this many dark pixels between it and the kept mask is kept (step 5)..."""
NEAR_FRACTION = 0.1
"""...or this fraction of the largest component's size, when that is more (step 5)."""
NOISY_GREY = 5.0
"""Pixel-to-pixel noise (grey levels) above which the frame is smoothed before thresholding (step 2)."""
MEDIAN_SIZE_PX = 3
"""Size of the median filter that smooths a noisy frame, pixels (step 2)."""
MASK_ASPECT_TOLERANCE = 0.01
"""A mask file whose width / height differs from the frame's by more than this is refused."""


@dataclass(frozen=True)
class Detection:
    """The object in one frame, in that frame's pixels (see the module docstring for the conventions)."""

    mask: np.ndarray
    """[H, W] bool foreground."""
    box: tuple[float, float, float, float]
    """x0, y0, x1, y1 of the mask's bounding box; x1, y1 are exclusive edges."""
    centroid: tuple[float, float]
    """(x, y) mean of the mask's pixel centres."""
    area: int
    """Number of mask pixels."""
    touches_border: bool
    """The mask reaches the outermost row or column: the frame may cut the object, so the box may be
    smaller than the object and its centre off."""
    threshold: float
    """Grey level (0-255, on the max-over-channels image, smoothed when the frame is noisy) that
    separated the object; NaN for a mask given by the user."""

    @property
    def size(self) -> float:
        """max(box width, box height), pixels: the apparent size that sets the range."""
        x0, y0, x1, y1 = self.box
        return max(x1 - x0, y1 - y0)

    @property
    def centre(self) -> tuple[float, float]:
        """(x, y) centre of the box."""
        x0, y0, x1, y1 = self.box
        return (0.5 * (x0 + x1), 0.5 * (y0 + y1))

    def around(self, margin: float) -> np.ndarray:
        """[H, W] bool: the box widened by ``margin`` times its size on every side, within the frame."""
        x0, y0, x1, y1 = self.box
        grow = margin * self.size
        height, width = self.mask.shape
        region = np.zeros((height, width), bool)
        region[max(0, math.floor(y0 - grow)):min(height, math.ceil(y1 + grow)),
               max(0, math.floor(x0 - grow)):min(width, math.ceil(x1 + grow))] = True
        return region


class MaskError(ValueError):
    """Bad user masks; the message is one line saying what is wrong and how to fix it."""


def grey_levels(image: np.ndarray) -> np.ndarray:
    """[H, W] float32 grey levels 0-255 of ``image``: the max over channels (step 1).

    ``image`` is [H, W, 3] or [H, W], ``uint8`` (0-255) or floating point (0-1, as renders are).
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"expected an image [H, W, 3] or [H, W], got shape {image.shape}")
    if image.dtype == np.uint8:
        grey = image.astype(np.float32)
    elif np.issubdtype(image.dtype, np.floating):
        grey = np.clip(image.astype(np.float32) * 255.0, 0.0, 255.0)
    else:
        raise ValueError(f"expected a uint8 (0-255) or float (0-1) image, got dtype {image.dtype}")
    return grey.max(axis=2) if grey.ndim == 3 else grey


def estimate_background(grey: np.ndarray, max_rounds: int = 50) -> tuple[float, float]:
    """(level, noise) of the background of ``grey`` [H, W] (0-255), as in step 2 of the module docstring.

    The clipped sample starts from the darkest quarter, so the estimate holds while the background fills
    more than about 40 % of the frame; the noise is floored at 1 grey level inside the clip so that a
    sample quantised to one or two levels can still grow to its true width.
    """
    values = np.asarray(grey, dtype=np.float32).ravel()
    sample = values[values <= np.quantile(values, 0.25)]
    level, noise = 0.0, 0.0
    for _ in range(max_rounds):
        level = float(np.median(sample))
        above = sample[sample > level] - level
        noise = 1.4826 * float(np.median(above)) if above.size else 0.0
        grown = values[values <= level + CLIP_UNITS * max(noise, 1.0)]
        if grown.size == sample.size:
            break
        sample = grown
    return level, noise


def pixel_noise(grey: np.ndarray) -> float:
    """Noise of ``grey`` [H, W] (0-255) from its horizontal neighbours: 1.4826 x the median absolute
    difference / sqrt(2), the sigma of white Gaussian noise. Smooth regions (the background, most of the
    object) dominate the median, and unlike the background sample's spread of :func:`estimate_background`
    it is 0 on a noise-free render, whose black background has no spread for the sample to find."""
    grey = np.asarray(grey, dtype=np.float32)
    if grey.shape[1] < 2:
        return 0.0
    return 1.4826 * float(np.median(np.abs(np.diff(grey, axis=1)))) / math.sqrt(2.0)


def foreground_threshold(level: float, noise: float) -> float:
    """Grey level above which a pixel is foreground (step 3)."""
    return level + min(max(NOISE_UNITS * noise, MIN_CONTRAST), MAX_CONTRAST)


def _kept_components(foreground: np.ndarray, min_area: int) -> np.ndarray | None:
    """The mask of the components that make the object (step 5), or None when the largest is too small."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(foreground.astype(np.uint8), connectivity=8)
    if count < 2:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    largest = int(np.argmax(areas)) + 1
    if areas[largest - 1] < min_area:
        return None
    largest_size = max(stats[largest, cv2.CC_STAT_WIDTH], stats[largest, cv2.CC_STAT_HEIGHT])
    keep = np.zeros(count, dtype=bool)
    keep[1:] = areas >= max(LARGE_FRACTION * areas[largest - 1], min_area)
    keep[largest] = True
    gap = max(NEAR_MIN_PX, int(round(NEAR_FRACTION * largest_size)))
    reach = np.ones((2 * gap + 3, 2 * gap + 3), dtype=np.uint8)  # chessboard distance <= gap + 1
    while True:
        kept = keep[labels]
        near = np.unique(labels[(cv2.dilate(kept.astype(np.uint8), reach) > 0) & ~kept])
        near = near[near > 0]
        if near.size == 0:
            return kept
        keep[near] = True


def detector_grey(image: np.ndarray) -> np.ndarray:
    """[H, W] float32: the grey levels the threshold is applied to (steps 1 and 2: the max over channels,
    median-filtered when the frame is noisy)."""
    grey = grey_levels(image)
    if pixel_noise(grey) > NOISY_GREY:
        grey = cv2.medianBlur(grey, MEDIAN_SIZE_PX)
    return grey


def find_object(image: np.ndarray, min_area: int = 12) -> Detection | None:
    """The object in ``image`` ([H, W, 3] uint8, or float 0-1), found as the module docstring says.

    None when no object is found (all black / only noise / largest component below ``min_area`` pixels).
    """
    grey = detector_grey(image)
    threshold = foreground_threshold(*estimate_background(grey))
    foreground = (grey > threshold).astype(np.uint8)
    closed = cv2.morphologyEx(foreground, cv2.MORPH_CLOSE, np.ones((3, 3), dtype=np.uint8))
    mask = _kept_components(closed, min_area)
    if mask is None:
        return None
    return _detection(mask, threshold)


def detection_from_mask(mask: np.ndarray) -> Detection | None:
    """The :class:`Detection` of a mask given by the user ([H, W], any non-zero is foreground); None if
    empty. Its ``threshold`` is NaN: no grey level was involved."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"expected a mask [H, W], got shape {mask.shape}")
    mask = mask != 0
    if not mask.any():
        return None
    return _detection(mask, math.nan)


def _detection(mask: np.ndarray, threshold: float) -> Detection:
    rows, cols = np.nonzero(mask)
    touches = bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())
    return Detection(mask=mask.astype(bool), box=(float(cols.min()), float(rows.min()), float(cols.max() + 1),
                                                  float(rows.max() + 1)),
                     centroid=(float(cols.mean() + 0.5), float(rows.mean() + 0.5)), area=int(rows.size),
                     touches_border=touches, threshold=float(threshold))


def read_masks(folder: Path, frame_names: list[str], shape: tuple[int, int]) -> list[np.ndarray]:
    """[H, W] bool masks for each frame from ``folder``, at the working resolution ``shape`` (H, W).

    The mask of frame ``img000001.png`` or ``img000001.jpg`` (any folder part of the name is ignored) is
    ``<folder>/img000001.png``: same stem, always PNG, because JPEG would blur the mask's edges. Any
    non-zero value is foreground. 8- or 16-bit grey is read as it is; RGB when any channel is non-zero;
    RGBA by its alpha channel when the alpha varies (a cut-out of the object) and by its colour channels
    when the alpha is constant (an opaque mask image saved with alpha). A mask of another size but the
    frame's aspect ratio (within 1 %) is resized with nearest neighbour, since the working resolution may
    differ from the files'. An empty mask is returned as it is (the object may be out of view); the caller
    decides. A missing folder, a frame with no mask, an unreadable file or another aspect ratio raise
    :class:`MaskError`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise MaskError(f"mask folder {folder} does not exist; pass the folder that holds one PNG mask per "
                        f"frame, named like the frame (img000001.png)")
    height, width = shape
    return [_read_mask(folder / f"{Path(name).stem}.png", name, height, width) for name in frame_names]


def _read_mask(path: Path, frame: str, height: int, width: int) -> np.ndarray:
    if not path.is_file():
        raise MaskError(f"frame {frame} has no mask: expected {path}; add it (same stem as the frame, PNG, "
                        f"non-zero = object) or leave out the mask folder")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise MaskError(f"cannot read mask {path} (frame {frame}); save it again as a grey, RGB or RGBA PNG")
    if data.ndim == 3 and data.shape[2] == 4 and data[..., 3].min() != data[..., 3].max():
        mask = data[..., 3] > 0
    elif data.ndim == 3:
        mask = (data[..., :3] > 0).any(axis=2)
    else:
        mask = data > 0
    file_h, file_w = mask.shape
    if abs((file_w / file_h) / (width / height) - 1.0) > MASK_ASPECT_TOLERANCE:
        raise MaskError(f"mask {path} (frame {frame}) is {file_w}x{file_h}, another aspect ratio than the "
                        f"frame at {width}x{height}; save the mask at the frame's size")
    if (file_h, file_w) != (height, width):
        mask = cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST_EXACT) > 0
    return mask
