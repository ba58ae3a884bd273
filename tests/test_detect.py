"""The object detector on drawn frames (no model): the box, the thin and detached parts, the specks it must
drop, the frames with nothing in them, and the user masks read from a folder."""

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from nerfinv_plugin.initialization.detect import (
    Detection,
    MaskError,
    detection_from_mask,
    estimate_background,
    find_object,
    foreground_threshold,
    grey_levels,
    read_masks,
)

H, W = 150, 240
BODY = (90, 55, 140, 95)  # x0, y0, x1, y1 (exclusive): 50 x 40 px
PANEL = (143, 69, 173, 81)  # 3 dark columns (140-142) right of the body; 30 x 12 px, under a fifth of the body
ANTENNA = ((100, 54), (80, 25))  # 1-px anti-aliased line from the body's top edge up and left, one channel
SHAPE_BOX = (80, 25, 173, 95)
HOT_PIXELS = ((10, 10), (230, 140), (20, 130), (200, 15), (235, 70))  # (x, y), all far from the object


def _noisy(clean: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    return np.clip(np.round(clean + rng.normal(0.0, sigma, clean.shape)), 0, 255).astype(np.uint8)


def _fill(image: np.ndarray, box: tuple[int, int, int, int], colour: tuple[float, float, float]) -> None:
    x0, y0, x1, y1 = box
    image[y0:y1, x0:x1] = colour


def _spacecraft(rng: np.random.Generator, sigma: float = 3.0, hot: bool = True) -> np.ndarray:
    """Body, a thin antenna and a small blue panel behind a 3-px gap, Gaussian noise and hot pixels."""
    clean = np.zeros((H, W, 3), dtype=np.float64)
    _fill(clean, BODY, (150.0, 170.0, 180.0))
    _fill(clean, PANEL, (30.0, 50.0, 160.0))
    cv2.line(clean, ANTENNA[0], ANTENNA[1], (0.0, 0.0, 120.0), 1, cv2.LINE_AA)  # one channel only
    image = _noisy(clean, sigma, rng)
    if hot:
        for x, y in HOT_PIXELS:
            image[y, x] = 255
    return image


def _assert_box(detection: Detection, expected: tuple[float, ...], tolerance: float) -> None:
    assert np.abs(np.subtract(detection.box, expected)).max() <= tolerance, (detection.box, expected)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_box_holds_antenna_and_panel_but_not_hot_pixels(rng: np.random.Generator) -> None:
    detection = find_object(_spacecraft(rng))
    assert detection is not None
    _assert_box(detection, SHAPE_BOX, 1.0)
    assert detection.mask[40, 90] or detection.mask[40, 91]  # halfway up the antenna
    assert detection.mask[75, 160]  # the panel
    assert not any(detection.mask[y, x] for x, y in HOT_PIXELS)
    assert not detection.touches_border
    assert detection.size == pytest.approx(SHAPE_BOX[2] - SHAPE_BOX[0], abs=1.0)
    assert 12.0 <= detection.threshold <= 30.0, detection.threshold


def test_centroid_matches_the_drawn_shape(rng: np.random.Generator) -> None:
    detection = find_object(_spacecraft(rng))
    # Analytic: the rectangles' pixel centres, plus the antenna as its segment's midpoint weighted by length.
    parts = [((BODY[0] + BODY[2]) / 2, (BODY[1] + BODY[3]) / 2, (BODY[2] - BODY[0]) * (BODY[3] - BODY[1])),
             ((PANEL[0] + PANEL[2]) / 2, (PANEL[1] + PANEL[3]) / 2, (PANEL[2] - PANEL[0]) * (PANEL[3] - PANEL[1])),
             ((ANTENNA[0][0] + ANTENNA[1][0]) / 2 + 0.5, (ANTENNA[0][1] + ANTENNA[1][1]) / 2 + 0.5,
              math.dist(*ANTENNA))]
    weights = np.array([w for _, _, w in parts])
    expected = (np.dot([x for x, _, _ in parts], weights) / weights.sum(),
                np.dot([y for _, y, _ in parts], weights) / weights.sum())
    assert np.allclose(detection.centroid, expected, atol=0.25), (detection.centroid, expected)
    assert detection.centre == pytest.approx(((SHAPE_BOX[0] + SHAPE_BOX[2]) / 2, (SHAPE_BOX[1] + SHAPE_BOX[3]) / 2),
                                             abs=1.0)


def test_centroid_of_a_disc_is_its_centre(rng: np.random.Generator) -> None:
    clean = np.zeros((H, W, 3))
    cv2.circle(clean, (117, 64), 20, (200.0, 200.0, 200.0), -1)
    detection = find_object(_noisy(clean, 3.0, rng))
    assert detection.centroid == pytest.approx((117.5, 64.5), abs=0.1)
    assert detection.box == (97.0, 44.0, 138.0, 85.0)


@pytest.mark.parametrize("sigma", [3.0, 0.0])
def test_jpeg_quality_80_keeps_the_box(sigma: float, rng: np.random.Generator) -> None:
    """With sensor noise and without (a clean render), where only the contrast floor holds the ringing."""
    image = _spacecraft(rng, sigma=sigma)
    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    detection = find_object(cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED))
    # Measured: 2-3 px more on the side of the saturated blue panel (ringing and chroma bleed at 10-15 % of
    # the edge's contrast, above the 12-level floor once JPEG has smoothed the noise), at q90 as at q60.
    _assert_box(detection, SHAPE_BOX, 3.0)


def test_half_resolution_keeps_the_antenna(rng: np.random.Generator) -> None:
    image = cv2.resize(_spacecraft(rng, hot=False), (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    detection = find_object(image)
    _assert_box(detection, tuple(v / 2 for v in SHAPE_BOX), 1.0)


def test_far_components_kept_only_when_large(rng: np.random.Generator) -> None:
    clean = np.zeros((H, W, 3))
    _fill(clean, (100, 50, 140, 90), (180.0, 180.0, 180.0))  # 1600 px
    _fill(clean, (20, 20, 24, 24), (180.0, 180.0, 180.0))  # 16 px, 76 px away: a star
    detection = find_object(_noisy(clean, 3.0, rng))
    assert detection.box == (100.0, 50.0, 140.0, 90.0)
    _fill(clean, (190, 60, 210, 80), (180.0, 180.0, 180.0))  # 400 px = a quarter, 50 px away: still the object
    detection = find_object(_noisy(clean, 3.0, rng))
    assert detection.box == (100.0, 50.0, 210.0, 90.0)


def test_dashed_antenna_is_followed_to_its_tip(rng: np.random.Generator) -> None:
    clean = np.zeros((H, W, 3))
    _fill(clean, (60, 60, 100, 90), (180.0, 180.0, 180.0))
    for x in range(103, 190, 6):  # 3-px dashes with 3-px gaps, too far apart for the closing
        clean[75, x:x + 3] = 120.0
    detection = find_object(_noisy(clean, 3.0, rng))
    assert detection.box == (60.0, 60.0, 190.0, 90.0)


def test_closing_fills_the_pinholes_of_a_dim_part(rng: np.random.Generator) -> None:
    """A shadowed part lit in one channel, 22 levels over black: noise drops about 4 % of its pixels under
    the threshold, scattered; the closing puts them back."""
    clean = np.zeros((H, W, 3))
    _fill(clean, (60, 40, 160, 110), (0.0, 0.0, 22.0))
    detection = find_object(_noisy(clean, 3.0, rng))
    assert detection.mask[41:109, 61:159].mean() > 0.995


def test_faint_fringe_of_a_clean_render_stays_out() -> None:
    """A noise-free render (a view of the model): a soft 2-px fringe of 10 then 6 levels round the body and a
    floater of 8 levels close by. The noise estimate is 0, so only the contrast floor keeps them out."""
    clean = np.zeros((H, W, 3))
    x0, y0, x1, y1 = BODY
    _fill(clean, (x0 - 2, y0 - 2, x1 + 2, y1 + 2), (6.0, 6.0, 6.0))
    _fill(clean, (x0 - 1, y0 - 1, x1 + 1, y1 + 1), (10.0, 10.0, 10.0))
    _fill(clean, BODY, (150.0, 170.0, 180.0))
    _fill(clean, (x1 + 4, y0, x1 + 8, y0 + 4), (8.0, 8.0, 8.0))
    detection = find_object(clean.astype(np.uint8))
    assert detection.box == tuple(float(v) for v in BODY)


@pytest.mark.parametrize("box", [(0, 40, 40, 100), (100, 0, 140, 30), (200, 40, W, 100), (100, 120, 140, H)])
def test_object_cut_by_the_border(box: tuple[int, int, int, int], rng: np.random.Generator) -> None:
    clean = np.zeros((H, W, 3))
    _fill(clean, box, (180.0, 180.0, 180.0))  # the rest lies outside the frame
    detection = find_object(_noisy(clean, 3.0, rng))
    assert detection.touches_border
    assert detection.box == tuple(float(v) for v in box)


@pytest.mark.parametrize("level,sigma", [(0.0, 0.0), (0.0, 3.0), (0.0, 10.0), (25.0, 6.0)])
def test_nothing_in_black_or_noise_only_frames(level: float, sigma: float, rng: np.random.Generator) -> None:
    image = _noisy(np.full((H, W, 3), level), sigma, rng)
    image[30, 30] = image[100, 200] = 255  # hot pixels alone are not an object
    assert find_object(image) is None


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("level,sigma", [(0.0, 1.0), (0.0, 3.0), (0.0, 6.0), (0.0, 10.0), (20.0, 3.0), (20.0, 10.0)])
def test_threshold_clears_the_noise_without_waste(level: float, sigma: float, shared: bool,
                                                  rng: np.random.Generator) -> None:
    """Per-channel or shared (grey sensor) noise, on black (clipped at 0) or grey backgrounds, with 30 % of
    the frame covered by an object spread over all grey levels."""
    clean = np.full((H, W, 3), level)
    clean[:45] += rng.uniform(10.0, 230.0, size=(45, W, 1))
    noise = rng.normal(0.0, sigma, (H, W, 1) if shared else (H, W, 3))
    grey = grey_levels(np.clip(np.round(clean + noise), 0, 255).astype(np.uint8))
    threshold = foreground_threshold(*estimate_background(grey))
    assert (grey[45:] > threshold).sum() <= 3  # background pixels above it, of 26,000
    assert threshold <= level + max(7.0 * sigma, 14.0), threshold


def test_float_image_reads_as_uint8(rng: np.random.Generator) -> None:
    image = _spacecraft(rng)
    assert find_object(image.astype(np.float32) / 255.0).box == find_object(image).box
    with pytest.raises(ValueError, match="shape"):
        find_object(np.zeros((H, W, 4), dtype=np.uint8))


def test_detection_from_mask_round_trip(rng: np.random.Generator) -> None:
    found = find_object(_spacecraft(rng))
    again = detection_from_mask(found.mask.astype(np.uint8) * 255)
    assert (again.box, again.centroid, again.area) == (found.box, found.centroid, found.area)
    assert np.array_equal(again.mask, found.mask) and math.isnan(again.threshold)
    mask = np.zeros((H, W), dtype=bool)
    mask[10:20, 30:50] = True
    made = detection_from_mask(mask)
    assert (made.box, made.centroid, made.size, made.centre, made.area) == ((30.0, 10.0, 50.0, 20.0), (40.0, 15.0),
                                                                             20.0, (40.0, 15.0), 200)
    assert not made.touches_border
    assert detection_from_mask(np.zeros((H, W), dtype=np.uint8)) is None


def _mask_image(scale: int) -> np.ndarray:
    mask = np.zeros((H * scale, W * scale), dtype=np.uint8)
    mask[40 * scale:90 * scale, 100 * scale:150 * scale] = 255
    mask[30 * scale:31 * scale, 60 * scale:100 * scale] = 1  # faint but non-zero; one frame pixel wide
    return mask


def test_read_masks_grey_rgb_rgba_and_resized(tmp_path: Path) -> None:
    expected = _mask_image(1) > 0
    cv2.imwrite(str(tmp_path / "img000001.png"), _mask_image(1))
    cv2.imwrite(str(tmp_path / "img000002.png"), _mask_image(2))  # twice the working resolution
    rgb = np.zeros((H, W, 3), dtype=np.uint8)
    rgb[..., 2] = _mask_image(1)  # only the red channel (BGR order on disk)
    cv2.imwrite(str(tmp_path / "img000003.png"), rgb)
    rgba = np.zeros((H, W, 4), dtype=np.uint8)
    rgba[..., 3] = _mask_image(1)  # a cut-out: black colour, the object in alpha
    cv2.imwrite(str(tmp_path / "img000004.png"), rgba)
    masks = read_masks(tmp_path, ["img000001.png", "img000002.jpg", "images/img000003.png", "img000004.png"],
                       (H, W))
    assert len(masks) == 4
    half = np.zeros((H // 2, W // 2), dtype=np.uint8)
    half[10:30:3, 20:61:7] = 255  # a grid of single pixels: nearest neighbour makes each a 2 x 2 block
    cv2.imwrite(str(tmp_path / "img000005.png"), half)
    (up,) = read_masks(tmp_path, ["img000005.png"], (H, W))
    assert np.array_equal(up, np.kron(half > 0, np.ones((2, 2), dtype=bool)))
    for mask in masks:
        assert mask.dtype == bool and mask.shape == (H, W)
    for name, mask in zip(("grey", "2x grey", "RGB", "RGBA cut-out"), masks):
        assert np.array_equal(mask, expected), (name, np.argwhere(mask != expected)[:5])


def test_read_masks_errors_name_the_problem(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "img000001.png"), _mask_image(1))
    with pytest.raises(MaskError, match="img000002") as missing:
        read_masks(tmp_path, ["img000001.png", "img000002.png"], (H, W))
    cv2.imwrite(str(tmp_path / "img000003.png"), np.zeros((H, H), dtype=np.uint8))
    with pytest.raises(MaskError, match="aspect ratio") as aspect:
        read_masks(tmp_path, ["img000003.jpg"], (H, W))
    (tmp_path / "img000004.png").write_bytes(b"not a png")
    with pytest.raises(MaskError, match="cannot read") as unreadable:
        read_masks(tmp_path, ["img000004.png"], (H, W))
    with pytest.raises(MaskError, match="does not exist") as no_folder:
        read_masks(tmp_path / "masks", ["img000001.png"], (H, W))
    for error in (missing, aspect, unreadable, no_folder):
        assert "\n" not in str(error.value)
