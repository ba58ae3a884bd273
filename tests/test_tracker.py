"""The inversion engine on the tiny toy model: convergence along a trajectory, the Monte Carlo schedule,
fixed mode, determinism, the motion prior and the starting-pose sources."""

import dataclasses
import io
import json

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nerfinv_plugin.data.sequences import SequenceError
from nerfinv_plugin.geometry.errors import rotation_error_deg
from nerfinv_plugin.geometry.frames import label_to_c2w_opencv, opencv_to_opengl
from nerfinv_plugin.geometry.se3 import exp_se3, geodesic_deg, log_se3
from nerfinv_plugin.initialization.detect import find_object
from nerfinv_plugin.inversion.optimizer import OptimizerConfig, PreparedFrame, centred, optimize_candidates
from nerfinv_plugin.inversion.sampling import PixelSampler
from nerfinv_plugin.inversion.session import InversionError, shirt_label_pool
from nerfinv_plugin.inversion.settings import InvertConfig, StartConfig
from nerfinv_plugin.inversion.starts import (
    around_prior,
    inerf_protocol_starts,
    sphere_shell,
    training_views,
    volume,
)
from nerfinv_plugin.inversion.tracker import (
    Frame,
    MonteCarloConfig,
    Tracker,
    TrackerState,
    _constant_velocity,
    keep_count,
)
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.model.render import Intrinsics
from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.trajectories import TrajectorySpec

RANGE_M = 5.0


@pytest.fixture(scope="module")
def toy_sequence(toy_run, tmp_path_factory):
    """The tiny toy model and a roe1 trajectory of the toy scene (4 degrees a frame) at the model's
    training resolution, with true poses in the model frame."""
    config, data = toy_run
    loaded = load_model(config, device="cpu")
    width = json.loads((data / "transforms.json").read_text())["w"]
    height = json.loads((data / "transforms.json").read_text())["h"]
    camera = speedplus_like_camera(width, height)
    out = tmp_path_factory.mktemp("toy_traj")
    spec = TrajectorySpec(kind="roe1", num_frames=5, range_m=RANGE_M)
    rendered = write_shirt_trajectories(out, "toy", [spec], camera, False, seed=0, spp=32, step=lambda: None)[0]
    intrinsics = Intrinsics.from_opencv(camera.matrix, width, height)
    frames = []
    for c2w_cv, path in zip(rendered.c2w_opencv, rendered.image_paths):
        image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        truth = torch.as_tensor(loaded.dataset_to_model(opencv_to_opengl(c2w_cv)), dtype=torch.float32)
        frames.append(Frame(image, intrinsics, path.name, truth))
    centre = torch.as_tensor(loaded.dataset_to_model(np.eye(4))[:3, 3], dtype=torch.float32)
    return loaded, frames, centre


_error = rotation_error_deg


def _starts(truth: torch.Tensor, centre: torch.Tensor, count: int, scale: float, seed: int = 0) -> torch.Tensor:
    """Starts 15 to 20 degrees off (turned about the target) and 5% of the range away."""
    return inerf_protocol_starts(truth, centre, count, 15.0, 20.0, 0.05 * RANGE_M * scale, seed)


def test_trajectory_mode_converges_within_five_frames(toy_sequence):
    loaded, frames, centre = toy_sequence
    start = _starts(frames[0].c2w_true, centre, 8, loaded.dataparser_scale)
    start_errors = _error(start, frames[0].c2w_true)
    assert start_errors.min() >= 15 - 1e-3 and start_errors.max() <= 20 + 1e-3
    tracker = Tracker(loaded, centre, OptimizerConfig(iterations=30), MonteCarloConfig(keep=(2, 1), spawn=2),
                      error_fn=_error)
    records = tracker.run(frames, start)
    errors = [float(_error(r.estimate[None], frames[r.frame_index].c2w_true)[0]) for r in records]
    assert min(errors) < 5.0, errors
    assert errors[-1] < 0.5 * float(start_errors.mean()), errors
    assert [r.candidates for r in records] == [8, 6, 3, 3, 3]  # keep 2 x (1 + 2 spawned), then 1 x 3


def test_fixed_mode_inverts_each_frame_alone_from_the_starts(toy_sequence):
    loaded, frames, centre = toy_sequence
    start = _starts(frames[0].c2w_true, centre, 6, loaded.dataparser_scale, seed=1)
    mc = MonteCarloConfig(mode="fixed", keep_fraction=0.5, spawn=1)
    tracker = Tracker(loaded, centre, OptimizerConfig(iterations=6), mc, pixels=128, eval_pixels=512, seed=3)
    records = tracker.run(frames[:2], start, steps_per_frame=4)
    assert [r.frame_index for r in records] == [0] * 4 + [1] * 4
    for frame in (records[:4], records[4:]):
        losses = [r.loss for r in frame]
        assert all(b <= a for a, b in zip(losses, losses[1:])), losses
        # keep 50% of 6 = 3 (+3 spawned), then 25% of 6 rounded = 2 (+2), then 1 (+1), at least 1: the
        # schedule restarts from the 6 starting poses on each frame
        assert [r.kept for r in frame] == [3, 2, 1, 1]
        assert [r.candidates for r in frame] == [6, 6, 4, 2]
    # The second frame alone gives what it gives in a run of its own seeded seed + 1.
    alone = Tracker(loaded, centre, OptimizerConfig(iterations=6), mc, pixels=128, eval_pixels=512, seed=4)
    again = alone.run(frames[1:2], start, steps_per_frame=4)
    assert [r.loss for r in again] == [r.loss for r in records[4:]]


def test_keep_count_schedules():
    thesis = MonteCarloConfig(keep=(3, 1))
    assert [keep_count(thesis, s, 15) for s in range(4)] == [3, 1, 1, 1]
    halving = MonteCarloConfig(keep_fraction=0.25)
    assert [keep_count(halving, s, 80) for s in range(6)] == [20, 10, 5, 2, 1, 1]
    assert keep_count(MonteCarloConfig(keep=(5,)), 0, 2) == 2  # never more than there are


def test_same_seed_same_numbers(toy_sequence):
    loaded, frames, centre = toy_sequence
    start = _starts(frames[0].c2w_true, centre, 3, loaded.dataparser_scale, seed=2)

    def run(seed: int):
        tracker = Tracker(loaded, centre, OptimizerConfig(iterations=3), MonteCarloConfig(keep=(1,), spawn=2),
                          pixels=64, eval_pixels=128, seed=seed)
        return tracker.run(frames[:2], start)

    a, b, c = run(7), run(7), run(8)
    for ra, rb in zip(a, b):
        assert ra.loss == rb.loss and torch.equal(ra.estimate, rb.estimate)
        assert np.array_equal(ra.result.history[-1].loss, rb.result.history[-1].loss)
    assert any(ra.loss != rc.loss for ra, rc in zip(a, c))


def test_motion_filter_changes_the_starts_and_a_resumed_run_gives_the_same_numbers(toy_sequence):
    loaded, frames, centre = toy_sequence
    start = _starts(frames[0].c2w_true, centre, 3, loaded.dataparser_scale, seed=2)

    def tracker(motion: str) -> Tracker:
        mc = MonteCarloConfig(keep=(2,), spawn=1, motion=motion)
        return Tracker(loaded, centre, OptimizerConfig(iterations=3), mc, pixels=64, eval_pixels=128, seed=5)

    whole = tracker("filter").run(frames[:4], start)
    plain = tracker("none").run(frames[:4], start)
    assert [r.loss for r in whole[:2]] == [r.loss for r in plain[:2]]  # no motion known before frame 2
    assert whole[2].loss != plain[2].loss  # from frame 2 on the candidates start at the prediction
    filtered = tracker("filter")
    state = filtered.begin(start)
    for k in range(2):
        filtered.step(state, frames[k], k)
    buffer = io.BytesIO()
    torch.save(state.state_dict(), buffer)  # as state.pt keeps it
    buffer.seek(0)
    resumed = TrackerState.from_state_dict(torch.load(buffer, weights_only=False))
    assert resumed.motion is not None and resumed.carried == state.carried
    rest = [filtered.step(resumed, frames[k], k) for k in (2, 3)]
    assert [r.loss for r in rest] == [r.loss for r in whole[2:]]
    assert torch.equal(rest[-1].estimate, whole[-1].estimate)


def test_constant_velocity_prediction_extrapolates_a_screw_motion():
    step = exp_se3(torch.tensor([[0.02, -0.05, 0.07, 0.1, 0.0, -0.03]], dtype=torch.float64))[0]
    first = exp_se3(torch.tensor([[0.3, 0.2, -0.1, 1.0, 2.0, 5.0]], dtype=torch.float64))[0]
    second = step @ first
    predicted = _constant_velocity(second.float(), (step @ second).float()).double() @ (step @ second)
    torch.testing.assert_close(predicted, step @ step @ second, atol=1e-5, rtol=1e-5)
    assert torch.allclose(log_se3(_constant_velocity(first.float(), second.float()).double()),
                          log_se3(step), atol=1e-5)


def test_starting_pose_sources(toy_run):
    _, data = toy_run
    rng = np.random.default_rng(0)
    views = training_views(data / "transforms_train.json", 5, rng)
    frames = json.loads((data / "transforms_train.json").read_text())["frames"]
    all_views = np.array([f["transform_matrix"] for f in frames])
    assert len(views) == 5 and all(any(np.allclose(v, a) for a in all_views) for v in views)
    target = np.array([0.1, -0.2, 0.3])
    cases = [(sphere_shell(50, 6.0, target, rng), 6.0, 6.0), (volume(200, 9.0, 2.0, target, rng), 2.0, 9.0)]
    for poses, lo, hi in cases:
        ranges = np.linalg.norm(poses[:, :3, 3] - target, axis=1)
        assert ranges.min() >= lo - 1e-9 and ranges.max() <= hi + 1e-9
        # OpenGL axes: the camera looks along -z, straight at the target.
        to_target = (target - poses[:, :3, 3]) / ranges[:, None]
        np.testing.assert_allclose(np.einsum("ni,ni->n", -poses[:, :3, 2], to_target), 1.0, atol=1e-9)
    far = volume(2000, 9.0, 0.0, target, rng)
    assert np.median(np.linalg.norm(far[:, :3, 3] - target, axis=1)) > 6.5  # uniform in volume: mostly far
    prior = sphere_shell(1, 5.0, target, rng)[0]
    noisy = around_prior(prior, 10, 10.0, 0.2, target, seed=0)
    assert np.allclose(noisy[0], prior) and not np.allclose(noisy[1], prior)
    rot = geodesic_deg(torch.as_tensor(noisy[:, :3, :3]), torch.as_tensor(prior[:3, :3]).expand(10, 3, 3))
    assert float(rot.max()) <= 10 * np.sqrt(3) + 1e-6


def test_shirt_label_starts_leave_out_the_frames_being_estimated(tmp_path):
    rotations = Rotation.random(8, random_state=0)
    labels = {}
    for name, first, count in (("roe1", 0, 5), ("roe2", 5, 3)):
        (tmp_path / name).mkdir()
        quats = rotations[first:first + count].as_quat()[:, [3, 0, 1, 2]]  # scalar first
        labels[name] = [{"filename": f"img{k:06d}.jpg", "q_vbs2tango_true": q.tolist(),
                         "r_Vo2To_vbs_true": [0.1 * k, 0.0, 5.0]} for k, q in enumerate(quats)]
        (tmp_path / name / f"{name}.json").write_text(json.dumps(labels[name]))
    config = InvertConfig(sequence=str(tmp_path / "roe1" / "synthetic"), start=1, stop=3, starts=StartConfig(count=6))
    pool = shirt_label_pool(config)
    expected = [labels["roe1"][k] for k in (0, 3, 4)] + labels["roe2"]
    assert len(pool) == 6
    for pose, label in zip(pool, expected):
        c2w = opencv_to_opengl(label_to_c2w_opencv(np.array(label["q_vbs2tango_true"]),
                                                   np.array(label["r_Vo2To_vbs_true"])))
        np.testing.assert_allclose(pose, c2w)
    with pytest.raises(InversionError, match="fewer than --starts.count 7"):
        shirt_label_pool(dataclasses.replace(config, starts=StartConfig(count=7)))
    with pytest.raises(SequenceError, match="not a SHIRT trajectory"):
        shirt_label_pool(dataclasses.replace(config, sequence=str(tmp_path)))


def test_a_candidate_whose_loss_turns_nan_is_dropped_and_the_rest_go_on(toy_sequence):
    loaded, frames, centre = toy_sequence
    start = _starts(frames[0].c2w_true, centre, 3, loaded.dataparser_scale, seed=4)
    start[1, 0, 3] = float("nan")
    frame = frames[0]
    sampler = PixelSampler("random", 64).prepare(frame.image)
    eval_pixels = torch.as_tensor(PixelSampler("random", 128).prepare(frame.image).sample(np.random.default_rng(0)))
    prepared = PreparedFrame.from_image(loaded, frame.image, frame.intrinsics, sampler, eval_pixels, centre)
    result = optimize_candidates(loaded, start, prepared, OptimizerConfig(iterations=3), np.random.default_rng(0))
    assert result.dropped == [1]
    assert torch.isinf(result.losses[1]) and torch.isfinite(result.losses[[0, 2]]).all()
    assert torch.isfinite(result.c2w[[0, 2]]).all()
    assert not torch.equal(result.c2w[0], start[0])  # the others kept optimizing


def _first_frame_step(toy_sequence, count: int, seed: int):
    """The model, the target centre, ``count`` starts off the first frame's truth and that frame prepared
    with 64 random pixels an iteration and 64 ranking pixels."""
    loaded, frames, centre = toy_sequence
    frame = frames[0]
    start = _starts(frame.c2w_true, centre, count, loaded.dataparser_scale, seed=seed)
    sampler = PixelSampler("random", 64).prepare(frame.image)
    eval_pixels = torch.as_tensor(PixelSampler("random", 64).prepare(frame.image).sample(np.random.default_rng(0)))
    return loaded, centre, start, PreparedFrame.from_image(loaded, frame.image, frame.intrinsics, sampler,
                                                           eval_pixels, centre)


@pytest.mark.parametrize("length", [1.0, 0.2])
def test_adams_translation_steps_are_in_units_of_the_length_given(toy_sequence, length):
    """Adam's first step moves every screw coordinate by its learning rate (its sign the gradient's): radians
    for the turn, ``length`` model units for the translation. With the object's radius as the length, the
    step sizes no longer depend on the scale the dataparser gave the scene."""
    loaded, centre, start, prepared = _first_frame_step(toy_sequence, 2, seed=7)
    config = OptimizerConfig(iterations=1, lr=0.01, polish_iterations=0)
    result = optimize_candidates(loaded, start, prepared, config, np.random.default_rng(0), length=length)
    to_centre, from_centre = centred(centre)
    screw = log_se3(from_centre @ result.c2w @ torch.linalg.inv(start) @ to_centre)  # [2, 6]: (w, v)
    assert torch.allclose(screw[:, :3].abs(), torch.full((2, 3), 0.01), rtol=0.02), screw
    assert torch.allclose(screw[:, 3:].abs(), torch.full((2, 3), 0.01 * length), rtol=0.02), screw


def test_averaging_ends_the_step_at_the_moving_average_of_the_iterates(toy_sequence):
    """With ``averaging`` the path is Adam's own (the same pixels, losses and iterates), and the step's
    final poses are the exponential moving average of the iterates' screw coordinates, computed here by
    hand from the iterates of the same step without averaging."""
    loaded, centre, start, prepared = _first_frame_step(toy_sequence, 3, seed=3)
    plain = optimize_candidates(loaded, start, prepared, OptimizerConfig(iterations=4, polish_iterations=0),
                                np.random.default_rng(1))
    averaged = optimize_candidates(loaded, start, prepared,
                                   OptimizerConfig(iterations=4, averaging=0.5, polish_iterations=0),
                                   np.random.default_rng(1))
    for a, b in zip(plain.history, averaged.history):
        assert np.array_equal(a.loss, b.loss) and np.array_equal(a.c2w, b.c2w)
    to_centre, from_centre = centred(centre)
    iterates = [torch.as_tensor(r.c2w) for r in plain.history[1:]] + [plain.c2w]  # after each iteration
    mean = torch.zeros(3, 6)
    for pose in iterates:
        mean = 0.5 * mean + 0.5 * log_se3((from_centre @ pose @ torch.linalg.inv(start) @ to_centre).double()).float()
    expected = to_centre @ exp_se3(mean) @ from_centre @ start
    assert torch.allclose(averaged.c2w, expected, atol=1e-5), (averaged.c2w - expected).abs().max()
    assert not torch.allclose(averaged.c2w, plain.c2w, atol=1e-4)  # it is not the last iterate


def test_pruning_stops_far_candidates_and_patience_ends_a_step_early(toy_sequence):
    loaded, frames, centre = toy_sequence
    frame = frames[0]
    near = _starts(frame.c2w_true, centre, 3, loaded.dataparser_scale, seed=5)
    far = inerf_protocol_starts(frame.c2w_true, centre, 3, 70.0, 90.0, 0.0, seed=6)
    start = torch.cat([near, far])
    sampler = PixelSampler("interest_region", 64).prepare(frame.image)
    eval_pixels = torch.as_tensor(PixelSampler("random", 128).prepare(frame.image).sample(np.random.default_rng(0)))
    prepared = PreparedFrame.from_image(loaded, frame.image, frame.intrinsics, sampler, eval_pixels, centre)
    config = OptimizerConfig(iterations=3, prune_every=2, prune_ratio=1.2)
    result = optimize_candidates(loaded, start, prepared, config, np.random.default_rng(0), min_candidates=2)
    # Pruned after the second iteration: every candidate above 1.2 x that iteration's best, but the best two.
    at_pruning = result.history[1].loss
    expected = {i for i in np.argsort(at_pruning)[2:] if at_pruning[i] > 1.2 * at_pruning.min()}
    assert expected and set(result.pruned) == expected and not result.dropped
    assert torch.isinf(result.losses[result.pruned]).all()
    assert torch.isfinite(result.losses[[i for i in range(6) if i not in expected]]).all()
    assert np.isinf(result.history[2].loss[result.pruned]).all()  # no longer rendered
    # Patience: a demanded 90% improvement per iteration never comes, so the step ends after 1 + 2.
    patient = OptimizerConfig(iterations=20, patience=2, min_improvement=0.9)
    short = optimize_candidates(loaded, near, prepared, patient, np.random.default_rng(0))
    assert len(short.history) == 3 and torch.isfinite(short.losses).all()


@pytest.mark.parametrize("sample_region", ["object", "image"])
def test_the_sample_region_decides_where_each_iterations_pixels_are_drawn(toy_sequence, monkeypatch, sample_region):
    """With sample_region object every iteration draws its pixels in the frame's object region (as the
    ranking pixels always do), and so does the polish after the ranking; with image, anywhere."""
    loaded, frames, centre = toy_sequence
    frame = dataclasses.replace(frames[0])
    height, width = frame.image.shape[:2]
    frame.object_region = np.zeros((height, width), bool)
    frame.object_region[10:30, 20:50] = True
    drawn: list[np.ndarray] = []
    original = PixelSampler.sample

    def spy(self, rng):
        pixels = original(self, rng)
        drawn.append(pixels)
        return pixels

    monkeypatch.setattr(PixelSampler, "sample", spy)
    start = _starts(frame.c2w_true, centre, 2, loaded.dataparser_scale, seed=8)
    tracker = Tracker(loaded, centre, OptimizerConfig(iterations=4), MonteCarloConfig(keep=(1,), spawn=1),
                      sampling="random", pixels=64, eval_pixels=128, sample_region=sample_region)
    tracker.run([frame], start)
    inside = [frame.object_region[p[:, 0], p[:, 1]] for p in drawn]
    # the ranking pixels are drawn first, then one set an iteration, then one a polishing iteration
    ranking, iterations, polish = inside[0], inside[1:5], inside[5:]
    assert ranking.all() and len(ranking) == 128
    assert all(len(i) == 64 for i in iterations) and len(polish) == OptimizerConfig().polish_iterations
    if sample_region == "object":  # the region's 600 pixels are fewer than the polish's 1,024: all of them
        assert all(i.all() for i in iterations) and all(i.all() and len(i) == 600 for i in polish)
    else:  # the region is 600 of 4,000 pixels: uniform draws over the image fall outside it
        assert not any(i.all() for i in iterations) and not any(i.all() for i in polish)
        assert all(len(i) == 1024 for i in polish)


def test_the_silhouette_weight_follows_the_last_outline_loss_under_a_trust_level(toy_sequence):
    """With ``silhouette_trust`` the term's weight on a step is ``weight x min(1, trust / L)**2``, ``L`` the last
    step's outline loss; the first step has none and keeps the weight, and a resumed run keeps ``L``."""
    loaded, frames, centre = toy_sequence
    masked = []
    for frame in frames[:3]:
        found = find_object(frame.image)
        masked.append(dataclasses.replace(frame, mask=found.mask, mask_threshold=found.threshold))
    start = _starts(frames[0].c2w_true, centre, 3, loaded.dataparser_scale, seed=2)

    def tracker(trust: float | None) -> Tracker:
        optimizer = OptimizerConfig(iterations=3, silhouette_weight=0.5, silhouette_trust=trust)
        return Tracker(loaded, centre, optimizer, MonteCarloConfig(keep=(1,), spawn=1), pixels=64, eval_pixels=128,
                       seed=3)

    fixed = tracker(None).run(masked, start)
    assert [r.silhouette_weight for r in fixed] == [0.5, 0.5, 0.5]
    assert all(r.outline_loss is not None and 0 < r.outline_loss < 1 for r in fixed)
    trust = 0.5 * min(r.outline_loss for r in fixed)  # below every outline loss: every later step is lowered
    adapted = tracker(trust)
    state = adapted.begin(start)
    first = adapted.step(state, masked[0], 0)
    assert first.silhouette_weight == 0.5 and first.loss == fixed[0].loss  # nothing known yet: as fixed
    buffer = io.BytesIO()
    torch.save(state.state_dict(), buffer)
    buffer.seek(0)
    resumed = TrackerState.from_state_dict(torch.load(buffer, weights_only=False))
    assert resumed.outline_loss == first.outline_loss
    second = adapted.step(resumed, masked[1], 1)
    assert second.silhouette_weight == pytest.approx(0.5 * (trust / first.outline_loss) ** 2, rel=1e-12)
    assert second.loss != fixed[1].loss
    high = tracker(2 * max(r.outline_loss for r in fixed)).run(masked, start)  # every outline counts as good
    assert [r.loss for r in high] == [r.loss for r in fixed]


def test_polishing_moves_the_best_candidate_alone_nearer_the_truth(toy_sequence):
    """The polish starts after the step is ranked: every candidate and loss is the plain step's but the best
    candidate, which the colour alone on 1024 fresh pixels an iteration brings nearer the truth."""
    loaded, frames, centre = toy_sequence
    frame = frames[0]
    start = inerf_protocol_starts(frame.c2w_true, centre, 3, 4.0, 6.0, 0.0, seed=11)
    sampler = PixelSampler("random", 64).prepare(frame.image)
    eval_pixels = torch.as_tensor(PixelSampler("random", 256).prepare(frame.image).sample(np.random.default_rng(0)))
    prepared = PreparedFrame.from_image(loaded, frame.image, frame.intrinsics, sampler, eval_pixels, centre)
    plain_config = OptimizerConfig(iterations=2, polish_iterations=0)
    plain = optimize_candidates(loaded, start, prepared, plain_config, np.random.default_rng(2))
    config = dataclasses.replace(plain_config, polish_iterations=40)
    polished = optimize_candidates(loaded, start, prepared, config, np.random.default_rng(2))
    best = int(torch.argmin(plain.losses))
    assert torch.equal(polished.losses, plain.losses) and len(polished.history) == len(plain.history)
    others = [i for i in range(3) if i != best]
    assert torch.equal(polished.c2w[others], plain.c2w[others])
    before, after = float(_error(plain.c2w[best], frame.c2w_true)), float(_error(polished.c2w[best], frame.c2w_true))
    assert after < 0.5 * before and after < 2.0, (before, after)
