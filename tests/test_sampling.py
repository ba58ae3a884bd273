"""Pixel samplers on images whose keypoints are known, and the per-candidate losses."""

import cv2
import numpy as np
import pytest
import torch

from nerfinv_plugin.inversion.losses import per_candidate_loss
from nerfinv_plugin.inversion.sampling import PixelSampler, sift_keypoints

BLOBS = [(20, 30), (60, 70), (75, 20), (30, 80)]


@pytest.fixture(scope="module")
def blob_image() -> np.ndarray:
    """Four bright discs on black: SIFT finds keypoints at (or right next to) their centres only."""
    image = np.zeros((100, 110, 3), np.uint8)
    for row, col in BLOBS:
        cv2.circle(image, (col, row), 5, (255, 255, 255), -1)
    return cv2.GaussianBlur(image, (5, 5), 1.0)


def _near_blobs(pixels: np.ndarray, radius: float) -> np.ndarray:
    dist = np.min([np.hypot(pixels[:, 0] - r, pixels[:, 1] - c) for r, c in BLOBS], axis=0)
    return dist <= radius


def test_sift_finds_the_blobs(blob_image):
    keypoints = sift_keypoints(blob_image)
    assert len(keypoints) >= len(BLOBS)
    assert _near_blobs(keypoints, 8).all()  # nothing on the empty background
    for row, col in BLOBS:
        assert np.hypot(keypoints[:, 0] - row, keypoints[:, 1] - col).min() <= 2


def test_interest_points_take_keypoints_first_then_fill_randomly(blob_image):
    keypoints = sift_keypoints(blob_image)
    sampler = PixelSampler("interest_point", count=len(keypoints)).prepare(blob_image)
    pixels = sampler.sample(np.random.default_rng(0))
    assert {tuple(p) for p in pixels} == {tuple(k) for k in keypoints}
    sampler = PixelSampler("interest_point", count=len(keypoints) + 300).prepare(blob_image)
    pixels = sampler.sample(np.random.default_rng(0))
    assert len({tuple(p) for p in pixels}) == len(pixels) == len(keypoints) + 300
    assert _near_blobs(pixels, 8).sum() < len(keypoints) + 30  # the fill lands mostly on the background


def test_interest_region_is_the_dilated_keypoints(blob_image):
    keypoints = sift_keypoints(blob_image)
    sampler = PixelSampler("interest_region", count=40, kernel_size=5).prepare(blob_image)
    region = sampler.keypoint_pixels
    assert len(keypoints) < region <= 25 * len(keypoints)
    for seed in range(5):
        pixels = sampler.sample(np.random.default_rng(seed))
        # Every pixel is within the 5x5 square (Chebyshev distance 2) of some keypoint.
        cheb = np.abs(pixels[:, None, :] - keypoints[None]).max(-1).min(1)
        assert (cheb <= 2).all() and len(np.unique(pixels, axis=0)) == 40


def test_random_sampling_respects_the_mask_and_covers_it(blob_image):
    mask = np.zeros(blob_image.shape[:2], bool)
    mask[10:40, 50:90] = True
    sampler = PixelSampler("random", count=500).prepare(blob_image, mask)
    pixels = sampler.sample(np.random.default_rng(1))
    assert mask[pixels[:, 0], pixels[:, 1]].all() and len(np.unique(pixels, axis=0)) == 500
    small = PixelSampler("random", count=5000).prepare(blob_image, mask).sample(np.random.default_rng(1))
    assert len(small) == mask.sum()  # never more than the allowed region, never repeated
    with pytest.raises(ValueError, match="does not match"):
        PixelSampler().prepare(blob_image, mask[:5])


def test_losses_against_hand_computation():
    predicted = torch.tensor([[[0.5, 0.5, 0.5], [0.0, 0.2, 1.0]], [[0.3, 0.3, 0.3], [0.3, 0.3, 0.3]]])
    observed = torch.tensor([[0.5, 0.3, 0.5], [0.0, 0.0, 0.5]])
    mse = per_candidate_loss("mse", predicted, observed)
    assert mse[0].item() == pytest.approx(((0.2**2) / 3 + (0.2**2 + 0.5**2) / 3) / 2)
    mape = per_candidate_loss("mape", predicted, observed)
    expected = ((0.2 / 0.31) / 3 + (0.2 / 0.01 + 0.5 / 0.51) / 3) / 2
    assert mape[0].item() == pytest.approx(expected, rel=1e-5)
    huber = per_candidate_loss("huber", predicted, observed)
    # 0.1 delta: 0.2 -> 0.1 * (0.2 - 0.05); 0.5 -> 0.1 * (0.5 - 0.05)
    assert huber[0].item() == pytest.approx((0.015 / 3 + (0.015 + 0.045) / 3) / 2)
    assert mse.shape == mape.shape == huber.shape == (2,)
