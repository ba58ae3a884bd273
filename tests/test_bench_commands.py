"""``ns-invert-bench perf|render|screw|bank`` (``viewer``: tests/test_bench_viewer.py, ``lightbox``:
tests/test_lightbox.py): the measuring functions on the tiny fixture model, at tiny
sizes, checked for what would show if they measured the wrong thing (the two ways rendering different
rays, the thesis' way running frozen, both screws turning about the same point, recall miscounted), and
that no benchmark leaves the model rendering differently; plus the command's shape."""

import json
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import psutil
import pytest
import torch
import tyro

from nerfinv_plugin.bench.gpu_check import compare_devices, render_with_gradient
from nerfinv_plugin.bench.observed import read_observed
from nerfinv_plugin.bench.perf import compare_loops, profile_ours, sampler_as_nerfstudio_loads_it, sweep
from nerfinv_plugin.bench.recall import bank_benchmark, bank_recall
from nerfinv_plugin.bench.render_speed import render_problem, render_speed
from nerfinv_plugin.bench.sampling import AS_TRAINED, Sampling
from nerfinv_plugin.bench.screw import screw_runs, summarize
from nerfinv_plugin.cli.bench import BankBench, Commands, GridBench, PerfBench, RenderBench, ScrewBench, entrypoint
from nerfinv_plugin.data.sequences import read_sequence
from nerfinv_plugin.geometry.se3 import exp_se3, geodesic_deg
from nerfinv_plugin.initialization.bank import BankConfig
from nerfinv_plugin.initialization.detect import find_object
from nerfinv_plugin.inversion.sampling import PixelSampler
from nerfinv_plugin.inversion.settings import RenderConfig
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.model.render import (
    MAX_CHUNK_RAYS,
    RenderSettings,
    bound_to_target,
    bytes_per_ray,
    ray_bundle,
    render,
)
from nerfinv_plugin.synth.scenes import SCENE_CENTRES

TOY_TARGET = tuple(float(v) for v in SCENE_CENTRES["toy"])
SUBCOMMANDS = ("grid", "perf", "gpu", "render", "screw", "bank", "viewer", "lightbox")


def test_help_lists_the_eight_subcommands_and_one_is_required(monkeypatch, capsys):
    shown = subprocess.run(["ns-invert-bench", "--help"], capture_output=True, text=True, check=True).stdout
    assert "{" + ",".join(SUBCOMMANDS) + "}" in shown
    assert all(f"• {name} " in shown for name in SUBCOMMANDS)  # each with its line of description
    monkeypatch.setattr(sys, "argv", ["ns-invert-bench"])
    with pytest.raises(SystemExit) as exit_info:
        entrypoint()
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "Missing subcommand" in err and all(name in err for name in SUBCOMMANDS)


def test_the_model_benchmarks_share_their_options():
    shared = ["--load-config", "run/config.yml", "--device", "cpu", "--threads", "1"]
    parsed = {name: tyro.cli(Commands, args=[name, *shared, *extra]) for name, extra in {
        "perf": ["--sequence", "s", "--render.nerf-samples", "12"], "render": ["--seed", "3"],
        "screw": ["--sequence", "s", "--seeds", "2"], "bank": ["--sequences", "a", "b"]}.items()}
    assert [type(p) for p in parsed.values()] == [PerfBench, RenderBench, ScrewBench, BankBench]
    assert all((str(p.load_config), p.device, p.threads) == ("run/config.yml", "cpu", 1) for p in parsed.values())
    assert parsed["perf"].render == Sampling(nerf_samples=12) and parsed["render"].seed == 3
    assert parsed["bank"].sequences == ("a", "b") and parsed["screw"].seeds == 2
    grid = tyro.cli(Commands, args=["grid", "g.yml", "--seeds", "0", "1"])
    assert isinstance(grid, GridBench) and str(grid.grid) == "g.yml" and grid.seeds == (0, 1)


def _settings(loaded) -> tuple:
    """What the benchmarks must leave as loaded: sample counts, chunk size, and the weights frozen without
    gradients."""
    sampler = loaded.model.proposal_sampler
    return (sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray,
            loaded.chunk_rays, any(p.requires_grad for p in loaded.model.parameters()),
            any(p.grad is not None for p in loaded.model.parameters()))


@pytest.fixture(scope="module")
def fresh(toy_run):
    """The fixture model as loaded, and its settings then."""
    loaded = load_model(toy_run[0], device="cpu")
    return loaded, _settings(loaded)


@pytest.fixture(scope="module")
def loaded(fresh):
    return fresh[0]


@pytest.fixture
def unchanged(fresh):
    """The model, failing the test if it leaves the model rendering otherwise than as loaded."""
    loaded, as_loaded = fresh
    assert _settings(loaded) == as_loaded
    yield loaded
    assert _settings(loaded) == as_loaded


def test_a_benchmark_sampling_is_a_render_settings_value_and_leaves_the_model_alone(unchanged):
    loaded = unchanged
    settings = Sampling(0.5, (6, 3), 5).settings(loaded, torch.zeros(3))
    assert (settings.proposal_samples, settings.nerf_samples) == ((6, 3), 5) and settings.chunk_rays >= 1
    assert settings.target_sphere[1] == pytest.approx(0.5 * loaded.dataparser_scale)
    trained = AS_TRAINED.settings(loaded, torch.zeros(3))
    assert (trained.target_sphere, trained.proposal_samples, trained.nerf_samples, trained.chunk_rays) == (
        None, None, None, None)


@pytest.fixture(scope="module")
def observed(loaded, toy_run):
    return read_observed(loaded, f"{toy_run[1]}:test", 0, TOY_TARGET)


def _weights_trainable_in_field(loaded) -> tuple[list[bool], torch.utils.hooks.RemovableHandle]:
    """Whether the field's weights were trainable each time it ran (a hook on its hash-grid MLP)."""
    seen: list[bool] = []
    handle = loaded.model.field.mlp_base.register_forward_hook(
        lambda module, args, out: seen.append(any(p.requires_grad for p in module.parameters())))
    return seen, handle


def test_perf_runs_the_thesis_way_unfrozen_and_ours_frozen_on_the_same_rays(unchanged, observed, monkeypatch):
    import nerfinv_plugin.bench.perf as perf

    loaded = unchanged
    ways: list[tuple[str, list[bool]]] = []
    thesis_step, our_loop = perf.thesis_step, perf.our_loop

    def spied(name, inner):
        def call(*args, **kwargs):
            seen, handle = _weights_trainable_in_field(loaded)
            try:
                return inner(*args, **kwargs)
            finally:
                handle.remove()
                ways.append((name, seen))
        return call

    monkeypatch.setattr(perf, "thesis_step", spied("thesis", thesis_step))
    monkeypatch.setattr(perf, "our_loop", spied("ours", our_loop))
    began = time.perf_counter()
    same = compare_loops(loaded, observed, 2, 32, 2, AS_TRAINED)
    wall = time.perf_counter() - began
    # One call per thesis iteration, in two parts, our step before, between and after them.
    assert [name for name, _ in ways] == ["ours", "thesis", "ours", "thesis", "ours"]
    assert all(all(seen) and seen for name, seen in ways if name == "thesis")
    assert all(not any(seen) and seen for name, seen in ways if name == "ours")
    assert (same.thesis.iterations, same.ours.iterations, len(same.ours_runs)) == (2, 2, 3)
    assert same.ours.seconds == sorted(t.seconds for t in same.ours_runs)[1]  # the median of our three
    assert same.thesis.rays_per_iteration == same.ours.rays_per_iteration == 64
    # Same starts, same first pixels, same sampling: the same losses (up to the fused hash forward).
    np.testing.assert_allclose(same.thesis.first_losses, same.ours.first_losses, rtol=1e-3, atol=1e-6)
    # ... and they are the starts' MSE on the first pixels the seed draws, rendered here.
    pixels = torch.as_tensor(PixelSampler("interest_region", 32).prepare(observed.image).sample(
        np.random.default_rng(0)))
    target = torch.as_tensor(observed.image, dtype=torch.float32)[pixels[:, 0], pixels[:, 1]] / 255.0
    with torch.no_grad():
        rgb = render(loaded, perf._starts(loaded, observed, 2, 0), observed.intrinsics, pixels).rgb
    np.testing.assert_allclose(same.ours.first_losses, ((rgb - target) ** 2).mean((1, 2)).numpy(), rtol=1e-3)
    # Each loop's time is within the call's, and the ratio is thesis over ours per iteration.
    assert 0 < same.thesis.seconds and 0 < same.ours.seconds
    assert same.thesis.seconds + sum(t.seconds for t in same.ours_runs) < wall
    assert same.ratio == pytest.approx(same.thesis.seconds / same.ours.seconds)

    bounded = compare_loops(loaded, observed, 2, 32, 1, Sampling(0.8, (8, 4), 8))
    np.testing.assert_allclose(bounded.thesis.first_losses, same.thesis.first_losses)  # the thesis' way as trained
    assert np.abs(bounded.ours.first_losses - same.ours.first_losses).max() < 0.3 * same.ours.first_losses.max()


def test_perf_sweep_and_profile(unchanged, observed):
    sampling = Sampling(0.8, (8, 4), 8)
    began = time.perf_counter()
    swept = sweep(unchanged, observed, [(1, 16), (2, 8)], 1, sampling)
    wall = time.perf_counter() - began
    assert [(p.candidates, p.pixels, p.timing.rays_per_iteration, p.timing.iterations) for p in swept.points] == [
        (1, 16, 16, 1), (2, 8, 16, 1)]
    # The chunk holds what the budget allows for a ray of the sampling swept (not of the model as loaded).
    per_ray = bytes_per_ray(unchanged, sampling.settings(unchanged, observed.centre))
    assert 0 < swept.memory_budget_bytes <= 0.25 * psutil.virtual_memory().total
    assert swept.chunk_rays == pytest.approx(min(MAX_CHUNK_RAYS, swept.memory_budget_bytes / (2 * per_ray)), rel=0.1)
    assert 0 < sum(p.timing.seconds for p in swept.points) < wall
    found = profile_ours(unchanged, observed, 2, 16, Sampling(0.8, (8, 4), 8), iterations=1, top=5)
    times = [op.self_cpu_s for op in found.operators]
    assert len(times) == 5 and times == sorted(times, reverse=True) and 0 < sum(times) <= found.cpu_s


def test_render_batched_and_per_candidate_agree_on_the_same_rays(unchanged, monkeypatch):
    loaded = unchanged
    problem = render_problem(loaded, 2, 24, 5.0, 40, 25, AS_TRAINED, on_target=False)
    assert problem.c2w.shape == (2, 3, 4) and len(set(map(tuple, problem.pixels.tolist()))) == 24
    seen, handle = _weights_trainable_in_field(loaded)
    try:
        speed = render_speed(loaded, problem, AS_TRAINED, repeats=2)
    finally:
        handle.remove()
    assert True in seen and False in seen  # the thesis' way trainable, ours frozen
    assert speed.rays == 48 and len(speed.thesis_s) == len(speed.ours_s) == 2
    assert speed.colour_diff_max < 1e-4, speed  # the same sampling: only the hash forward differs
    assert all(0 < t < 60 for t in speed.thesis_s + speed.ours_s)
    assert speed.ratio == pytest.approx(np.median(speed.thesis_s) / np.median(speed.ours_s))

    bounded = Sampling(0.8, (8, 4), 8)
    aimed = render_problem(loaded, 2, 24, 5.0, 40, 25, bounded, on_target=True)
    sphere = RenderSettings(bounded.sphere(loaded, aimed.centre))
    hits = bound_to_target(sphere, ray_bundle(loaded, aimed.c2w[:1], aimed.intrinsics, aimed.pixels))
    assert bool(hits.all())  # every pixel drawn is on the target sphere
    fewer = render_speed(loaded, aimed, bounded, repeats=1)
    assert 0 < fewer.colour_diff_mean < 0.05, fewer  # fewer samples on bounded rays: close, not equal


def test_screw_rows_carry_both_parameterisations_from_the_same_starts(unchanged, observed):
    began = time.perf_counter()
    runs = screw_runs(unchanged, observed, 2, 3, 15.0, 20.0, 0.05, [0, 1])
    wall = time.perf_counter() - began
    assert [(r.seed, r.origin) for r in runs] == [(0, "target"), (0, "world"), (1, "target"), (1, "world")]
    for target, world in (runs[0:2], runs[2:4]):
        assert target.start_deg == world.start_deg and 15.0 <= target.start_deg <= 20.0
        assert target.median_deg != world.median_deg  # they turn about different points
    assert runs[0].start_deg != runs[2].start_deg
    assert all(np.isfinite([r.best_deg, r.median_deg]).all() and r.seconds > 0 for r in runs)
    assert sum(r.seconds for r in runs) < wall  # each run timed on its own step, not on the whole call
    rows = summarize(runs)
    assert [r.origin for r in rows] == ["target", "world"]
    assert rows[1].best_deg == pytest.approx(np.median([runs[1].best_deg, runs[3].best_deg]))


class _PlannedBank:
    """An initializer whose hypotheses are set by hand: frame k of the usable ones gets plan[k % 3]."""

    def __init__(self, loaded, frames, centre: np.ndarray):
        self.loaded, self.centre, self.calls = loaded, centre, 0
        self.truths = {f.image.tobytes(): f.c2w_true for f in frames}

    def _turned(self, c2w: torch.Tensor, degrees: float) -> torch.Tensor:
        roll = exp_se3(torch.tensor([[0.0, 0.0, float(np.deg2rad(degrees)), 0.0, 0.0, 0.0]]))[0]
        out = c2w @ roll  # the camera turned about its own axis: that many degrees off
        centre = torch.as_tensor(self.centre, dtype=torch.float32)
        out[:3, 3] = centre + 1.1 * (c2w[:3, 3] - centre)  # 10% too far
        return out

    def poses(self, image, detection, intrinsics, count):
        truth = torch.as_tensor(self.loaded.dataset_to_model(self.truths[image.tobytes()]), dtype=torch.float32)
        plan = ([0.0, 30.0], [30.0, 5.0], [40.0, 50.0])[self.calls % 3]
        self.calls += 1
        return torch.stack([self._turned(truth, d) for d in plan[:count]])


def test_recall_counts_as_a_hand_count(loaded, toy_run):
    sequence = read_sequence(f"{toy_run[1]}:test")
    frames = list(sequence.frames)
    frames[1] = replace(frames[1], c2w_true=None)  # no truth: left out, not matched
    usable = [f for f in frames if f.c2w_true is not None and (d := find_object(f.image)) is not None
              and not d.touches_border]
    assert len(usable) >= 3
    bank = _PlannedBank(loaded, usable, loaded.point_to_model(np.asarray(TOY_TARGET)))
    recall = bank_recall(loaded, bank, replace(sequence, frames=frames), "toy", 2, 15.0)
    n = len(usable)
    firsts = [k % 3 == 0 for k in range(n)]
    anys = [k % 3 != 2 for k in range(n)]
    best = [(0.0, 5.0, 40.0)[k % 3] for k in range(n)]
    assert (recall.frames, recall.skipped, bank.calls) == (n, len(frames) - n, n)
    assert recall.top1 == pytest.approx(np.mean(firsts)) and recall.topk == pytest.approx(np.mean(anys))
    assert recall.median_best_deg == pytest.approx(np.median(best), abs=0.05)
    assert recall.median_range_error == pytest.approx(0.1, abs=1e-3) and len(recall.match_s) == n
    assert float(geodesic_deg(bank._turned(torch.eye(4), 5.0)[None, :3, :3], torch.eye(3)[None])) == \
        pytest.approx(5.0, abs=0.01)


def test_bank_benchmark_builds_reads_and_rebuilds_its_cache(unchanged, toy_run, tmp_path, monkeypatch):
    monkeypatch.setenv("NERFINV_CACHE", str(tmp_path / "cache"))
    config, render = BankConfig(subdivisions=1, in_plane=4), RenderConfig(target_radius_m=0.8)
    spec = f"{toy_run[1]}:test"

    def bench(rebuild: bool):
        return bank_benchmark(unchanged, [spec, spec], TOY_TARGET, config, render, 5, 15.0, rebuild=rebuild)

    began = time.perf_counter()
    first = bench(False)
    wall = time.perf_counter() - began
    again, rebuilt = bench(False), bench(True)
    assert (first.built, again.built, rebuilt.built) == (True, False, True)
    assert 0 < first.build_s <= first.ready_s < wall and again.build_s == first.build_s  # the cache keeps it
    assert again.ready_s < first.build_s  # read from the cache, not rendered
    assert first.radius_m == pytest.approx(0.8) and first.radius_given
    assert 0 < first.entries <= config.views * config.in_plane and again.entries == first.entries
    usable = sum(d is not None and not d.touches_border for d in map(find_object, (
        f.image for f in read_sequence(spec).frames)))
    assert [(r.frames, r.skipped) for r in first.recalls] == [(usable, 6 - usable)] * 2 and usable >= 3
    a, b = first.recalls
    assert (a.top1, a.topk, a.median_best_deg) == (b.top1, b.topk, b.median_best_deg)
    top1, topk = first.overall()
    assert 0 <= top1 <= topk <= 1 and topk == pytest.approx(a.topk)


def test_the_command_prints_each_table_and_refuses_a_frame_without_truth(toy_run, tmp_path, monkeypatch, capsys):
    config, data = toy_run
    shared = ["--load-config", str(config), "--device", "cpu"]
    commands = {"render": ["--candidates", "2", "--pixels", "8", "--repeats", "1", "--width", "40", "--height", "25"],
                "screw": ["--sequence", f"{data}:test", "--candidates", "2", "--iterations", "2", "--seeds", "1"]}
    for name, extra in commands.items():
        monkeypatch.setattr(sys, "argv", ["ns-invert-bench", name, *shared, *extra])
        entrypoint()
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ")]
    assert "ratio (thesis time / ours)" in out and all(line.endswith(" |") for line in rows)  # rows unwrapped
    assert any(line.startswith("| thesis: per-candidate") for line in rows)
    assert [line.split(" | ")[0] for line in rows if line.startswith(("| target", "| world"))] == ["| target",
                                                                                                   "| world"]
    monkeypatch.setattr(sys, "argv", ["ns-invert-bench", "perf", *shared, "--sequence",
                                      str(_folder_without_truth(data, tmp_path))])
    with pytest.raises(SystemExit) as exit_info:
        entrypoint()
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "has no ground-truth pose" in err and len(err.strip().splitlines()) == 1


def _folder_without_truth(data: Path, tmp_path: Path) -> Path:
    """A held-out view of the fixture as an image folder with camera.json and no poses.json."""
    meta = json.loads((data / "transforms_test.json").read_text())
    folder = tmp_path / "no-truth"
    folder.mkdir()
    image = cv2.imread(str(data / "test" / "r_000.png"))  # RGB, the alpha dropped
    cv2.imwrite(str(folder / "f0.png"), image)
    height, width = image.shape[:2]
    focal = 0.5 * width / np.tan(0.5 * meta["camera_angle_x"])
    (folder / "camera.json").write_text(json.dumps({"Nu": width, "Nv": height, "distCoeffs": [0.0] * 5,
                                                    "cameraMatrix": [[focal, 0, width / 2], [0, focal, height / 2],
                                                                     [0, 0, 1]]}))
    return folder


def test_the_device_check_agrees_on_one_device_and_catches_another_model(loaded, observed, toy_run, monkeypatch,
                                                                          capsys):
    """``ns-invert-bench gpu``'s comparison, run CPU against CPU: the same checkpoint agrees exactly; a copy
    whose field's hash table is scaled does not. Where there is no CUDA the command says so (exit 2)."""
    sampling = Sampling(0.6, (8, 4), 8)
    start, pixels = observed.starts(3, 5.0, 15.0, 0.01, 0), torch.tensor([[20, 30], [25, 40], [30, 45]])
    first = render_with_gradient(loaded, start, observed, pixels, sampling)[2]
    again = render_with_gradient(loaded, start, observed, pixels, sampling)[2]
    assert not start.requires_grad and np.abs(first).max() > 0  # the caller's poses stay as they were
    assert np.array_equal(first, again)  # no gradient carried over from the first call
    same = compare_devices(loaded, load_model(toy_run[0], device="cpu"), observed, 3, 64, sampling)
    assert same.agrees and same.gradient_scale > 1e-4
    assert (same.rgb_max_abs, same.accumulation_max_abs, same.gradient_max_rel) == (0.0, 0.0, 0.0)
    other = load_model(toy_run[0], device="cpu")
    with torch.no_grad():
        other.model.field.mlp_base.model[0].hash_table.mul_(1.05)
    changed = compare_devices(loaded, other, observed, 3, 64, sampling)
    assert not changed.agrees and changed.rgb_max_abs > 1e-3
    if not torch.cuda.is_available():
        monkeypatch.setattr(sys, "argv", ["ns-invert-bench", "gpu", "--load-config", str(toy_run[0]), "--sequence",
                                          f"{toy_run[1]}:test"])
        with pytest.raises(SystemExit) as exit_info:
            entrypoint()
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and "no CUDA device here" in err and len(err.strip().splitlines()) == 1


def test_loaded_nerfacto_evaluates_its_proposals_without_a_graph_and_the_thesis_side_with_one(loaded, observed,
                                                                                              monkeypatch):
    """At the trained step nerfacto's sampler runs its proposal networks under no_grad (nothing back-propagates
    through them); the thesis' loop gets the step nerfstudio's loader leaves, where it records their graph."""
    seen: list[bool] = []
    fns = loaded.model.density_fns

    def spy(fn):
        def density_fn(positions, times=None):
            seen.append(torch.is_grad_enabled())
            return fn(positions, times)
        return density_fn

    monkeypatch.setattr(loaded.model, "density_fns", [spy(fn) for fn in fns])
    c2w = observed.truth[None].clone().requires_grad_(True)
    pixels = torch.tensor([[10, 20], [25, 40]])
    render(loaded, c2w, observed.intrinsics, pixels).rgb.sum().backward()
    assert seen == [False, False] and float(c2w.grad.abs().sum()) > 0
    seen.clear()
    with sampler_as_nerfstudio_loads_it(loaded.model):
        render(loaded, c2w, observed.intrinsics, pixels)
    assert seen == [True, True]
    seen.clear()
    render(loaded, c2w, observed.intrinsics, pixels)
    assert seen == [False, False]  # the trained step is back
