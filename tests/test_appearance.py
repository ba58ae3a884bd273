"""The per-frame gain and bias: the fit recovers a planted mapping, degenerate fits stay sane, and the
tracker fits it on a frame whose colours were changed, keeps it for the frame, and saves it with its state;
the per-candidate mapping: each candidate's fit is its own, and with it a tinted frame matches the model at
the truth."""

import json

import numpy as np
import pytest
import torch

from nerfinv_plugin.geometry.errors import rotation_error_deg
from nerfinv_plugin.inversion.appearance import MAX_GAIN, GainBias, fit_each
from nerfinv_plugin.inversion.optimizer import OptimizerConfig, PreparedFrame, candidate_losses, optimize_candidates
from nerfinv_plugin.inversion.sampling import PixelSampler
from nerfinv_plugin.inversion.starts import inerf_protocol_starts
from nerfinv_plugin.inversion.tracker import Frame, Tracker, TrackerState
from nerfinv_plugin.model.render import AS_TRAINED, render_image

GAIN = torch.tensor([0.8, 0.76, 0.68])  # exposure 0.8 times a warm light, 1 : 0.95 : 0.85
BIAS = torch.tensor([0.04, 0.03, 0.05])


def test_the_fit_recovers_a_planted_gain_and_bias():
    rendered = torch.rand(500, 3, generator=torch.Generator().manual_seed(0))
    fitted = GainBias.fit(rendered, GAIN * rendered + BIAS)
    assert torch.allclose(fitted.gain, GAIN, atol=1e-5) and torch.allclose(fitted.bias, BIAS, atol=1e-5)
    assert torch.allclose(fitted.to_model(GAIN * rendered + BIAS), rendered, atol=1e-5)
    again = GainBias.from_dict(json.loads(json.dumps(fitted.to_dict())))
    assert torch.equal(again.gain, fitted.gain) and torch.equal(again.bias, fitted.bias)


def test_a_flat_render_fits_only_the_bias_and_a_wild_gain_is_clamped():
    flat = torch.full((100, 3), 0.2)
    fitted = GainBias.fit(flat, torch.rand(100, 3, generator=torch.Generator().manual_seed(1)))
    assert torch.equal(fitted.gain, torch.ones(3))
    rendered = torch.rand(100, 3, generator=torch.Generator().manual_seed(2))
    assert float(GainBias.fit(rendered, 40 * rendered).gain.max()) == MAX_GAIN


def test_each_candidate_gets_the_mapping_of_its_own_render():
    observed = torch.rand(400, 3, generator=torch.Generator().manual_seed(3)) * 0.6 + 0.2
    other_gain, other_bias = torch.tensor([1.3, 1.0, 0.9]), torch.tensor([-0.05, 0.0, 0.02])
    rendered = torch.stack([(observed - BIAS) / GAIN, (observed - other_bias) / other_gain])
    gain, bias = fit_each(rendered, observed)
    assert torch.allclose(gain, torch.stack([GAIN, other_gain]), atol=1e-5)
    assert torch.allclose(bias, torch.stack([BIAS, other_bias]), atol=1e-5)
    single = GainBias.fit(rendered[1], observed)
    assert torch.equal(single.gain, gain[1]) and torch.equal(single.bias, bias[1])


@pytest.fixture(scope="module")
def toy_frame(toy_held_out):
    """The toy model, a held-out camera, its true pose and the model's own clean image there."""
    loaded, intrinsics, truth, centre = toy_held_out
    return loaded, intrinsics, truth, render_image(loaded, truth.numpy(), intrinsics), centre


def test_the_tracker_fits_the_frame_s_mapping_and_keeps_it_for_the_frame(toy_frame):
    loaded, intrinsics, truth, clean, centre = toy_frame
    lab = np.clip(clean * GAIN.numpy() + BIAS.numpy(), 0, 1)
    frame = Frame((lab * 255).round().astype(np.uint8), intrinsics, "lab", truth)
    config = OptimizerConfig(iterations=2, appearance="gain-bias")
    tracker = Tracker(loaded, centre, config, pixels=64, eval_pixels=512)
    state = tracker.begin(truth[None].repeat(3, 1, 1))
    tracker.step(state, frame, 0)
    fitted = state.appearance
    assert fitted is not None
    # Rendered at the true pose the model gives back the clean image, so the fit is the planted mapping
    # up to 8-bit rounding and the clipping at 0.
    assert torch.allclose(fitted.gain, GAIN, atol=0.03) and torch.allclose(fitted.bias, BIAS, atol=0.01)
    tracker.step(state, frame, 0)  # a second step on the same frame keeps its mapping
    assert state.appearance is fitted
    restored = TrackerState.from_state_dict(state.state_dict())
    assert torch.equal(restored.appearance.gain, fitted.gain)
    plain = tracker.begin(truth[None].repeat(3, 1, 1))
    Tracker(loaded, centre, OptimizerConfig(iterations=2), pixels=64, eval_pixels=512).step(plain, frame, 0)
    assert plain.appearance is None


def test_the_candidate_mapping_matches_a_tinted_frame_at_the_truth(toy_frame):
    loaded, intrinsics, truth, clean, _ = toy_frame
    pixels = torch.stack(torch.meshgrid(torch.arange(0, clean.shape[0], 4), torch.arange(0, clean.shape[1], 4),
                                        indexing="ij"), -1).reshape(-1, 2)
    tinted = torch.as_tensor(clean[pixels[:, 0], pixels[:, 1]], dtype=torch.float32) * GAIN + BIAS
    colours = torch.zeros(1, pixels.shape[0], 3)
    as_observed = candidate_losses(loaded, truth[None], intrinsics, pixels, tinted, "mse", False, AS_TRAINED,
                                   rendered=colours)
    gain, bias = fit_each(colours, tinted)
    assert torch.allclose(gain[0], GAIN, atol=0.03) and torch.allclose(bias[0], BIAS, atol=0.01)
    mapped = candidate_losses(loaded, truth[None], intrinsics, pixels, tinted, "mse", False, AS_TRAINED,
                              mapping=(gain, bias))
    # the same render, mapped: the tint was the whole difference (rendering is not bit-exact: a margin)
    assert float(mapped[0]) < 0.05 * float(as_observed[0]) and float(mapped[0]) < 1e-4


def test_candidates_with_their_own_mapping_come_in_on_a_tinted_frame(toy_frame):
    loaded, intrinsics, truth, clean, centre = toy_frame
    tinted = (np.clip(clean * GAIN.numpy() + BIAS.numpy(), 0, 1) * 255).round().astype(np.uint8)
    box = np.zeros(clean.shape[:2], bool)
    rows, cols = np.nonzero(clean.max(-1) > 0.05)
    box[rows.min():rows.max() + 1, cols.min():cols.max() + 1] = True
    sampler = PixelSampler("random", 256).prepare(tinted, box)
    eval_pixels = torch.as_tensor(PixelSampler("random", 1024).prepare(tinted, box).sample(np.random.default_rng(0)))
    frame = PreparedFrame.from_image(loaded, tinted, intrinsics, sampler, eval_pixels, centre)
    start = inerf_protocol_starts(truth, centre, 4, 6.0, 6.0, 0.02, seed=1)
    config = OptimizerConfig(appearance="candidate-gain-bias", silhouette_weight=0.0)
    result = optimize_candidates(loaded, start, frame, config, np.random.default_rng(0))
    before, after = rotation_error_deg(start, truth), rotation_error_deg(result.c2w, truth)
    assert float(after.max()) < float(before.min()), (before, after)  # every candidate came in
    assert float(after[torch.argmin(result.losses)]) < 3.0, after
    # the tint is absorbed: the best candidate's ranking loss is what the model's own image would give
    # (as observed it stays near the tint's 5e-3)
    assert float(result.losses.min()) < 1e-4, result.losses
