"""The per-frame gain and bias: the fit recovers a planted mapping, degenerate fits stay sane, and the
tracker fits it on a frame whose colours were changed, keeps it for the frame, and saves it with its state."""

import json

import numpy as np
import pytest
import torch

from nerfinv_plugin.inversion.appearance import MAX_GAIN, GainBias
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.tracker import Frame, Tracker, TrackerState
from nerfinv_plugin.model.render import render_image

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
