"""The SE(3) motion filter against analytic motions with known noise: it must estimate and predict better
than the raw estimates (never amplify their noise), follow a motion that is not constant-velocity, reject a
single 30-degree outlier, restart when the motion really jumps, and carry its state through a resume."""

import io
import math
from types import SimpleNamespace

import numpy as np
import torch

from nerfinv_plugin.geometry.se3 import exp_se3, geodesic_deg, log_se3
from nerfinv_plugin.inversion.motion_filter import (
    MotionFilter,
    MotionFilterConfig,
    MotionState,
    PoseMeasurement,
    adjoint,
    left_jacobian,
)
from nerfinv_plugin.inversion.tracker import MonteCarloConfig, Tracker, TrackerState

NOISE_DEG, NOISE_M = 2.0, 0.1
"""The simulated estimates' noise: about the optimizer's per-frame errors (docs/benchmarks.md)."""
START = exp_se3(torch.tensor([0.3, -0.2, 0.1, 0.4, -0.3, 5.0], dtype=torch.float64))
"""A camera 5 units from the target (target frame)."""
AXIS = torch.tensor([0.2, 1.0, 0.3], dtype=torch.float64) / math.sqrt(1.13)


def _spin(rates_deg: list[float]) -> list[torch.Tensor]:
    """True poses: the camera turning about the target (a twist with no linear part) by ``rates_deg[k]``
    between frames k and k + 1."""
    poses = [START]
    for rate in rates_deg:
        xi = torch.cat([AXIS * math.radians(rate), torch.zeros(3, dtype=torch.float64)])
        poses.append(exp_se3(xi) @ poses[-1])
    return poses


def _noisy(truth: list[torch.Tensor], seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    sigma = torch.tensor([math.radians(NOISE_DEG)] * 3 + [NOISE_M] * 3, dtype=torch.float64)
    return [exp_se3(torch.randn(6, generator=g, dtype=torch.float64) * sigma) @ t for t in truth]


def _deg(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(geodesic_deg(a[:3, :3], b[:3, :3]))


def _noise_covariance() -> torch.Tensor:
    return torch.diag(torch.tensor([math.radians(NOISE_DEG)] * 3 + [NOISE_M] * 3, dtype=torch.float64) ** 2)


def _track(motion_filter: MotionFilter, measured: list[torch.Tensor]):
    """Filtered poses, predictions of the next frame, and the verdicts, frame by frame."""
    filtered, predicted, verdicts, state = [], [], [], None
    for z in measured:
        prior = None if state is None else motion_filter.predict(state)
        state, verdict = motion_filter.update(prior, PoseMeasurement(z, _noise_covariance()))
        filtered.append(state.pose)
        predicted.append(motion_filter.predict(state).pose)
        verdicts.append(verdict)
    return filtered, predicted, verdicts


def _median(values: list[float]) -> float:
    return float(torch.tensor(values).median())


def _compare(truth: list[torch.Tensor], measured: list[torch.Tensor], config: MotionFilterConfig,
             burn_in: int = 5) -> dict[str, float]:
    """Median rotation errors after ``burn_in`` frames: the raw estimates, the filtered poses, and, for the
    next frame, the filter's prediction, the constant-velocity one and none (this frame's estimate)."""
    filtered, predicted, verdicts = _track(MotionFilter(config), measured)
    frames = range(burn_in, len(truth) - 1)
    velocity = [measured[k] @ torch.linalg.inv(measured[k - 1]) @ measured[k] for k in frames]
    return {"raw": _median([_deg(measured[k], truth[k]) for k in frames]),
            "filtered": _median([_deg(filtered[k], truth[k]) for k in frames]),
            "predicted": _median([_deg(predicted[k], truth[k + 1]) for k in frames]),
            "no-prior": _median([_deg(measured[k], truth[k + 1]) for k in frames]),
            "constant-velocity": _median([_deg(v, truth[k + 1]) for v, k in zip(velocity, frames)]),
            "rejected": sum(v == "rejected" for v in verdicts)}


def test_adjoint_and_left_jacobian_against_the_matrices():
    t = exp_se3(torch.tensor([0.4, -0.1, 0.7, 1.0, 2.0, -3.0], dtype=torch.float64))
    xi = torch.tensor([0.05, 0.02, -0.07, 0.1, -0.2, 0.3], dtype=torch.float64)
    torch.testing.assert_close(exp_se3(adjoint(t) @ xi), t @ exp_se3(xi) @ torch.linalg.inv(t))
    e = torch.tensor([1e-6, -2e-6, 3e-6, 2e-6, 1e-6, -1e-6], dtype=torch.float64)
    # exp(xi + e) exp(xi)^-1 = exp(J e): checked to second order in |e| (1e-12), far below J - I (~0.05 |e|)
    moved = log_se3(exp_se3(xi + e) @ torch.linalg.inv(exp_se3(xi)))
    torch.testing.assert_close(moved, left_jacobian(xi) @ e, atol=1e-11, rtol=0)
    assert (moved - e).abs().max() > 1e-8


def test_filter_beats_the_raw_estimates_on_a_steady_spin_with_noise():
    truth = _spin([4.0] * 40)
    measured = _noisy(truth, seed=0)
    got = _compare(truth, measured, MotionFilterConfig(accel_deg=0.2, accel_m=0.01))
    assert got["filtered"] < 0.7 * got["raw"], got
    # never amplifies the noise: the prediction is closer to the next frame than the raw estimate is to its own
    assert got["predicted"] < got["raw"], got
    assert got["predicted"] < 0.5 * got["constant-velocity"], got  # the old prior doubles the noise
    assert got["constant-velocity"] > got["raw"], got
    assert got["rejected"] <= 1, got  # Gaussian noise of the stated size passes the gate


def test_filter_follows_an_accelerating_spin():
    rates = [1.0 + 0.25 * k for k in range(40)]  # 1 to 10.75 degrees per frame: not constant-velocity
    truth = _spin(rates)
    measured = _noisy(truth, seed=1)
    got = _compare(truth, measured, MotionFilterConfig(accel_deg=0.5, accel_m=0.01))
    assert got["filtered"] < 0.8 * got["raw"], got
    # the next frame predicted about as well as the raw estimates know their own frame (the unmodelled
    # acceleration costs some), far better than either old way
    assert got["predicted"] < 0.6 * got["no-prior"], got  # no prior lags the motion by 1-11 degrees
    assert got["predicted"] < 0.6 * got["constant-velocity"], got
    assert got["rejected"] <= 1, got


def test_a_single_30_degree_outlier_is_rejected_and_the_filter_stays_on_its_prediction():
    truth = _spin([4.0] * 30)
    measured = _noisy(truth, seed=2)
    measured[20] = exp_se3(torch.cat([AXIS.flip(0) * math.radians(30.0), torch.zeros(3, dtype=torch.float64)])) \
        @ measured[20]
    assert abs(_deg(measured[20], truth[20]) - 30) < 4
    motion_filter = MotionFilter(MotionFilterConfig(accel_deg=0.2, accel_m=0.01))
    filtered, _, verdicts = _track(motion_filter, measured)
    assert verdicts[20] == "rejected" and verdicts.count("rejected") == 1, verdicts
    assert verdicts[21:] == ["accepted"] * (len(measured) - 21)
    assert _deg(filtered[20], truth[20]) < 3.0  # its prediction, not the outlier
    # the state after the rejection is exactly the prediction (one rejection counted)
    state = None
    for z in measured[:20]:
        state, _ = motion_filter.update(None if state is None else motion_filter.predict(state),
                                        PoseMeasurement(z, _noise_covariance()))
    prior = motion_filter.predict(state)
    after, verdict = motion_filter.update(prior, PoseMeasurement(measured[20], _noise_covariance()))
    assert verdict == "rejected" and after.rejections == 1
    assert torch.equal(after.pose, prior.pose) and torch.equal(after.covariance, prior.covariance)


def test_a_real_jump_restarts_the_filter_after_max_rejections():
    truth = _spin([4.0] * 30)
    jump = exp_se3(torch.cat([AXIS.flip(0) * math.radians(40.0), torch.zeros(3, dtype=torch.float64)]))
    truth = truth[:15] + [jump @ t for t in truth[15:]]  # from frame 15 on the target really is elsewhere
    measured = _noisy(truth, seed=3)
    filtered, _, verdicts = _track(MotionFilter(MotionFilterConfig(accel_deg=0.2, max_rejections=3)), measured)
    assert verdicts[15:19] == ["rejected"] * 3 + ["restarted"], verdicts
    assert _deg(filtered[25], truth[25]) < 4.0


def test_measurement_covariance_from_the_kept_candidates():
    motion_filter = MotionFilter(MotionFilterConfig(measurement_deg=2.0, measurement_m=0.1), scale=0.5)
    floor = torch.diag(torch.tensor([math.radians(2.0)] * 3 + [0.05] * 3, dtype=torch.float64) ** 2)
    same = motion_filter.fit_covariance(START, START.repeat(3, 1, 1), torch.tensor([1.0, 1.1, 1.2]))
    torch.testing.assert_close(same, floor)
    turn = torch.zeros(6, dtype=torch.float64)
    turn[0] = math.radians(10.0)
    other = exp_se3(turn) @ START
    kept = torch.stack([START, other, START])
    near = motion_filter.fit_covariance(START, kept, torch.tensor([1.0, 1.0, 1.0]))
    far = motion_filter.fit_covariance(START, kept, torch.tensor([1.0, 4.0, 1.0]))
    expected_near = floor.clone()
    expected_near[0, 0] += math.radians(10.0) ** 2 / 3  # weights 1, 1, 1
    expected_far = floor.clone()
    expected_far[0, 0] += math.radians(10.0) ** 2 * 0.25 / 2.25  # weights 1, 1/4, 1
    torch.testing.assert_close(near, expected_near)
    torch.testing.assert_close(far, expected_far)


def _state_after(motion_filter: MotionFilter, measured: list[torch.Tensor]) -> MotionState:
    state = None
    for z in measured:
        state, _ = motion_filter.update(None if state is None else motion_filter.predict(state),
                                        PoseMeasurement(z, _noise_covariance()))
    return state


def test_filter_state_round_trips_through_the_tracker_state():
    truth = _spin([4.0] * 12)
    measured = _noisy(truth, seed=4)
    motion_filter = MotionFilter(MotionFilterConfig())
    state = TrackerState(3, torch.eye(4).repeat(2, 1, 1), np.random.default_rng(0),
                         torch.Generator().manual_seed(0), last_frame=8, last_estimate=torch.eye(4),
                         motion=_state_after(motion_filter, measured[:9]),
                         motion_before=motion_filter.predict(_state_after(motion_filter, measured[:8])))
    buffer = io.BytesIO()
    torch.save(state.state_dict(), buffer)  # as the run folder's state.pt keeps it
    buffer.seek(0)
    loaded = TrackerState.from_state_dict(torch.load(buffer, weights_only=False))
    for name in ("motion", "motion_before"):
        a, b = getattr(state, name), getattr(loaded, name)
        assert torch.equal(a.pose, b.pose) and torch.equal(a.twist, b.twist)
        assert torch.equal(a.covariance, b.covariance) and a.rejections == b.rejections
    # continuing from the loaded state gives the numbers the uninterrupted filter gives
    go_on = [loaded.motion]
    for z in measured[9:]:
        go_on.append(motion_filter.update(motion_filter.predict(go_on[-1]), PoseMeasurement(z, _noise_covariance()))[0])
    assert torch.equal(go_on[-1].pose, _state_after(motion_filter, measured).pose)
    empty = TrackerState.from_state_dict(TrackerState(0, torch.eye(4)[None], np.random.default_rng(0),
                                                      torch.Generator()).state_dict())
    assert empty.motion is None and empty.motion_before is None


def test_tracker_starts_each_frame_at_the_prediction_and_counts_a_frame_once():
    centre = torch.tensor([0.1, -0.2, 0.3])
    to_world = torch.eye(4, dtype=torch.float64)
    to_world[:3, 3] = centre.double()
    tracker = Tracker(SimpleNamespace(dataparser_scale=1.0), centre,
                      monte_carlo=MonteCarloConfig(motion="filter",
                                                   motion_filter=MotionFilterConfig(accel_deg=0.2, accel_m=0.01)))
    truth = [to_world @ t for t in _spin([4.0] * 9)]
    offset = exp_se3(torch.tensor([0.0, 0.05, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    bank = exp_se3(torch.tensor([3.0, 0.0, 0.0, 0.0, 0.0, 5.0])).float()
    state = TrackerState(0, torch.eye(4)[None], np.random.default_rng(0), torch.Generator())
    for k in [0, 1, 2, 3, 4, 5, 7]:  # frame 6 is skipped (no object, or the clock)
        if k > 0:
            carried = state.candidates.clone()
            state.candidates = torch.cat([carried, bank[None]])  # a bank hypothesis joins before the step
            tracker._predict(state, k)
            assert torch.equal(state.candidates[-1], bank)  # not moved: it is this frame's already
            if k > 1:  # the filter has a motion: the best starts at the prediction, the others as seen from it
                predicted = to_world @ state.motion_before.pose
                torch.testing.assert_close(state.candidates[0].double(), predicted, atol=1e-5, rtol=0)
                first, second = state.candidates[0].double(), state.candidates[1].double()
                torch.testing.assert_close(torch.linalg.inv(first) @ second,
                                           torch.linalg.inv(carried[0].double()) @ carried[1].double(),
                                           atol=1e-5, rtol=0)
            if k >= 4:  # it has learnt the 4-degree turn, over the skipped frame too
                assert _deg(state.candidates[0].double(), truth[k]) < 1.0, k
        kept = torch.stack([truth[k], offset @ truth[k]]).float()
        tracker._measure(state, kept[0], kept, torch.tensor([1.0, 1.0]))
        state.candidates, state.carried, state.last_frame, state.last_estimate = kept, 2, k, kept[0]
    # a second step on the same frame measures it again from the same prediction: once or twice, same filter
    once = state.motion
    tracker._measure(state, kept[0], kept, torch.tensor([1.0, 1.0]))
    assert torch.equal(state.motion.pose, once.pose) and torch.equal(state.motion.covariance, once.covariance)
