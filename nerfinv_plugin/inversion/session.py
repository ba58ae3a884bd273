"""One ``ns-invert`` run: load the model and the sequence, choose starting poses, run the Monte Carlo
tracker frame after frame, and write every result into the run folder as soon as it exists.

The schedule is the tracker's (:meth:`Tracker.schedule`): frame ``k`` gets ``steps_per_frame`` consecutive
steps. In ``trajectory`` mode the candidates carry over from frame to frame (the thesis' method); in
``fixed`` mode every frame starts again from the starting poses (parallel iNeRF on each image alone, the
baseline). Which frames are taken is the clock's (:mod:`nerfinv_plugin.inversion.clock`): every frame in
turn (``--clock frames``), or the newest one observed when the previous step ends (``--clock realtime``,
the frames skipped interpolated). After every step the whole state is
saved, so a run stopped anywhere (Ctrl-C, a crash, a full disk) resumes at the step it lost and ends with
the numbers an uninterrupted run would have given (with the realtime clock: when it charges a fixed cost).
"""

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TypeVar, assert_never

import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.data.sequences import Sequence, read_sequence, shirt_trajectory_poses
from nerfinv_plugin.geometry.errors import label_error, rotation_error_deg
from nerfinv_plugin.geometry.frames import c2w_opencv_to_label, label_to_c2w_opencv, opencv_to_opengl
from nerfinv_plugin.geometry.se3 import geodesic_deg
from nerfinv_plugin.initialization.detect import Detection, MaskError, detection_from_mask, find_object, read_masks
from nerfinv_plugin.initialization.extent import framed_radius, object_radius
from nerfinv_plugin.initialization.initializer import Initializer, rendered_silhouette, silhouette_iou
from nerfinv_plugin.inversion import starts
from nerfinv_plugin.inversion.clock import Clock, fraction_between, interpolated_pose
from nerfinv_plugin.inversion.optimizer import IterationRecord, StepResult, iterations_per_step
from nerfinv_plugin.inversion.reanchor import reanchor, silhouette_anchor
from nerfinv_plugin.inversion.settings import InvertConfig, RenderConfig, read_config, write_config
from nerfinv_plugin.inversion.tracker import Frame, StepRecord, Tracker, TrackerState
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.model.render import RenderSettings, render_settings
from nerfinv_plugin.results.folder import CONFIG, RunFolder
from nerfinv_plugin.results.records import BankSummary, FrameResult, RunSummary, StepRow
from nerfinv_plugin.results.summary import summarize

T = TypeVar("T")
R = TypeVar("R")

BOUNDED_PROPOSAL_SAMPLES = (16, 8)
"""Samples per proposal level when rays are bounded to the object. nerfacto-tiny's default training
(2,000 iterations) learns an outline that (8, 4) / 8 samples blur: (16, 8) / 16 renders it within 0.002 of the
trained (64, 32) / 24 in the silhouette term, at a fraction of their cost (docs/benchmarks.md, sessions
29-31). A model trained for fewer iterations is softer and does better with ``--render.proposal-samples 8 4
--render.nerf-samples 8`` (docs/nerfacto-tiny.md)."""
BOUNDED_NERF_SAMPLES = 16
RANK_MARGIN = 0.25
"""With ``--rank-region object``, candidates are ranked on pixels of the object's box widened by this
fraction of its size on every side: a candidate that puts the object beside it is still seen."""


def _timed_each(work: Callable[[T], R], items: list[T]) -> tuple[list[R], list[float]]:
    """``work`` of every item, and the seconds each took."""
    results, seconds = [], []
    for item in items:
        tic = time.perf_counter()
        results.append(work(item))
        seconds.append(time.perf_counter() - tic)
    return results, seconds


class InversionError(Exception):
    """Settings that cannot work together; the message says what to change."""


@dataclass
class Events:
    """What a front end hears while a run goes on (progress bars, messages). All optional."""

    begin: Callable[[int, int, int], None] = lambda total_steps, done_steps, iterations: None
    iteration: Callable[[int, IterationRecord], None] = lambda iteration, record: None
    step: Callable[[StepRow], None] = lambda step: None
    frame: Callable[[FrameResult], None] = lambda row: None
    warn: Callable[[str], None] = lambda message: None
    info: Callable[[str], None] = lambda message: None
    bank: Callable[[int], Callable[[int], None]] = lambda views: (lambda done: None)
    """Called before the view bank is rendered with its number of views; returns what to call after each
    batch with the number of views it rendered."""
    loaded: Callable[[LoadedModel, list[Frame], RenderSettings], None] = lambda loaded, frames, settings: None
    """Called once the model and the frames are loaded and the run folder exists, with the render settings
    of the run (the viewer draws the scene and renders the best candidate with them)."""
    step_begin: Callable[[int, int], None] = lambda step, frame: None
    """Called before each Monte Carlo step with its index and its frame's index (the viewer shows that frame)."""
    ranked: Callable[[int, StepRecord], None] = lambda step, record: None
    """Called after each Monte Carlo step, once it is saved, with its index and record: the candidates'
    final poses and losses, and how many the step kept (the candidate trail and the viewer)."""


def sequence_name(spec: str) -> str:
    """A readable experiment name: ``roe1``, ``scene-test``, ``images``."""
    path, _, split = str(spec).partition(":")
    name = Path(path.rstrip("/")).name or "sequence"
    return f"{name}-{split}" if split else name


def new_run_folder(config: InvertConfig) -> Path:
    if config.load_config is None or config.sequence is None:
        raise InversionError("give --load-config (the trained run's config.yml) and --sequence, "
                             "or --resume RUN_DIR")
    timestamp = config.timestamp or datetime.now().strftime("%Y-%m-%d_%H%M%S")
    return config.output_dir / (config.name or sequence_name(config.sequence)) / "nerfinv" / timestamp


def dataset_pose_to_label(c2w_opengl: np.ndarray) -> tuple[list[float], list[float]]:
    """SHIRT / SPEED+ label (q scalar-first, r in metres) of a dataset-frame camera-to-world pose."""
    q, r = c2w_opencv_to_label(opencv_to_opengl(c2w_opengl))  # the axis flip is its own inverse
    return [float(v) for v in q], [float(v) for v in r]


def shirt_label_pool(c: InvertConfig) -> np.ndarray:
    """Every labelled pose [M, 4, 4] of the SHIRT root of ``c.sequence`` but the frames the run estimates:
    where ``--starts.source shirt-labels`` draws from."""
    own, poses = shirt_trajectory_poses(c.sequence)
    estimated = set(range(len(poses[own]))[c.start:c.stop:c.stride])
    pool = [pose for name, trajectory in poses.items() for k, pose in enumerate(trajectory)
            if name != own or k not in estimated]
    if len(pool) < c.starts.count:
        raise InversionError(f"--starts.source shirt-labels: the SHIRT root of {c.sequence} has {len(pool)} labelled "
                             f"poses outside this run's frames, fewer than --starts.count {c.starts.count}")
    return np.array(pool)


def attitude_deg(a: Tensor, b: Tensor) -> Tensor:
    """Degrees between every attitude of ``a`` [N, 4, 4] and every one of ``b`` [M, 4, 4]: [N, M]."""
    return geodesic_deg(a[:, None, :3, :3].double(), b[None, :, :3, :3].to(a.device).double())


def bound_rays(loaded: LoadedModel, centre: Tensor, render: RenderConfig) -> tuple[RenderSettings, float | None]:
    """The run's render settings: rays bounded to a sphere about ``centre`` (model frame) that holds the
    object, measured on the model unless ``render`` gives its radius, and the fewer samples that then
    suffice, unless ``render`` says otherwise. Returns them and the radius in dataset metres when it was
    measured here; ``loaded`` is not changed."""
    measured, sphere = None, None
    if render.bound:
        if render.target_radius_m is not None:
            radius = render.target_radius_m * loaded.dataparser_scale
        else:
            radius = object_radius(loaded, centre.to(loaded.device))
            measured = radius / loaded.dataparser_scale
        sphere = (centre.to(loaded.device), radius)
    proposal, nerf = render.proposal_samples, render.nerf_samples
    sampler = getattr(loaded.model, "proposal_sampler", None)
    if render.bound and proposal is None and nerf is None and sampler is not None:
        proposal = BOUNDED_PROPOSAL_SAMPLES if len(sampler.num_proposal_samples_per_ray) == 2 else None
        nerf = BOUNDED_NERF_SAMPLES
    return render_settings(loaded, sphere, proposal, nerf), measured


@dataclass
class Inversion:
    """A run folder and the settings it runs with."""

    config: InvertConfig
    folder: RunFolder
    events: Events = field(default_factory=Events)

    @classmethod
    def create(cls, config: InvertConfig, events: Events | None = None) -> "Inversion":
        """A new run; its folder is made once the model and the sequence have loaded."""
        path = new_run_folder(config)
        if RunFolder(path).load() is not None:
            raise InversionError(f"{path} already holds results: continue it with --resume {path}, "
                                 "or give another --timestamp")
        return cls(config, RunFolder(path), events or Events())

    @classmethod
    def resume(cls, path: Path, events: Events | None = None) -> "Inversion":
        if not (Path(path) / CONFIG).is_file():
            raise InversionError(f"{path} is not an ns-invert run folder (no {CONFIG}); give the folder "
                                 "printed when the run started")
        return cls(read_config(Path(path) / CONFIG), RunFolder(path), events or Events())

    def run(self) -> RunSummary:
        """Run (or continue) to the end of the sequence; return the summary."""
        c = self.config
        loaded = load_model(c.load_config, device=c.device)
        sequence = read_sequence(c.sequence, c.start, c.stop, c.stride, c.resolution, c.camera, c.frame_interval_s)
        clock = self._clock(sequence)
        frames = [Frame(f.image, sequence.intrinsics, f.name, None if f.c2w_true is None else
                        torch.as_tensor(loaded.dataset_to_model(f.c2w_true), dtype=torch.float32))
                  for f in sequence.frames]
        detections, detect_s = self._detections(sequence)
        setup = time.perf_counter()  # from here on, everything is compute the clock is charged for
        for frame, detection in zip(frames, detections):
            frame.mask = None if detection is None else detection.mask
            frame.mask_threshold = float("nan") if detection is None else detection.threshold
            frame.object_region = None if detection is None else detection.around(RANK_MARGIN)
        centre = torch.as_tensor(loaded.point_to_model(np.asarray(c.target)), dtype=torch.float32)
        settings, radius = bound_rays(loaded, centre, c.render)
        if radius is not None:
            self.events.info(f"object radius {radius:.3g} m, read off the model's density (rays are bounded to it)")
        framing = None  # read once (unbounded rays measure the density grid): the bank frames it, Adam steps in it
        if c.starts.source == "bank" or c.optimizer.translation_unit == "object" or c.reanchor:
            framing = framed_radius(loaded, centre, settings)
        initializer = None
        if c.starts.source == "bank":
            initializer = self._initializer(loaded, centre, settings, framing)
        start = self._starts(loaded, sequence, centre, detections, initializer)
        setup_s = time.perf_counter() - setup
        size = framing if c.optimizer.translation_unit == "object" else None
        tracker = Tracker(loaded, centre, c.optimizer, c.monte_carlo, c.sampling, c.pixels, c.eval_pixels,
                          c.seed, rotation_error_deg, settings, c.sample_region, c.rank_region, size)
        self.folder.path.mkdir(parents=True, exist_ok=True)
        if not (self.folder.path / CONFIG).is_file():
            write_config(self.folder.path / CONFIG, dataclasses.replace(c, resume=None))
        self.events.loaded(loaded, frames, settings)
        saved = self.folder.load()
        if saved is None:
            rows, steps, elapsed, resumed = [], [], 0.0, None
            clock.charge(setup_s)
        else:
            rows, steps, elapsed = saved.rows, saved.steps, saved.elapsed_s
            resumed = TrackerState.from_state_dict(saved.tracker)
            self.folder.export(rows, steps)  # catch up if the last run stopped between the two writes
            # the recorded clock (runs from before it: their compute time)
            clock.now_s = steps[-1].clock_end_s if steps[-1].clock_end_s is not None else elapsed / c.clock_speed
        visited = [s.index for i, s in enumerate(steps) if i == 0 or steps[i - 1].index != s.index]
        total = len(frames) * c.steps_per_frame  # realtime: at most
        self.events.begin(total, len(steps), iterations_per_step(c.optimizer))
        for step_index, k, within, state in tracker.schedule(clock.visits(visited), start, c.steps_per_frame,
                                                              resumed, len(steps)):
            begun = clock.now_s
            self.events.step_begin(step_index, k)
            tic = time.perf_counter()
            detection = detections[k]
            reinitialized, watched = False, 0
            if detection is None:
                self.events.warn(f"frame {k} ({frames[k].name}): no object found (nothing bright enough on the "
                                 "dark background, or too small); keeping the prediction")
                estimate = state.last_estimate if state.last_estimate is not None else start[0]
                record = StepRecord(k, estimate, state.last_loss, 0, StepResult(estimate[None], torch.zeros(1)))
            else:
                if within == 0 and k > 0:
                    if initializer is not None:
                        opacity = None if c.lost_iou == 0 else rendered_silhouette(
                            loaded, settings, state.candidates[0], frames[k].intrinsics)
                        reinitialized, watched = self._ask_bank(initializer, state, frames[k], detection, opacity)
                    if c.reanchor:
                        self._reanchor(loaded, settings, state, frames[k], detections, k, centre, framing)
                record = tracker.step(state, frames[k], k, self.events.iteration)
            wall = time.perf_counter() - tic
            elapsed += wall
            clock.charge(wall + (detect_s[k] if within == 0 else 0.0), len(record.result.history))
            steps.append(self._step_row(record, k, self._frame_number(k), step_index, wall, reinitialized, watched,
                                        begun, clock.now_s))
            if record.result.dropped:
                self.events.warn(f"frame {k} ({frames[k].name}): dropped candidate(s) "
                                 f"{', '.join(map(str, record.result.dropped))} (non-finite pose, loss or "
                                 "gradient); going on with the others")
            finished = []
            if within == c.steps_per_frame - 1:
                own = [s for s in steps if s.index == k]
                row = self._frame_row(loaded, record, sequence, k, sum(s.wall_time_s for s in own), elapsed,
                                      detection is not None, any(s.reinitialized for s in own),
                                      sum(s.bank_added for s in own), clock)
                finished = self._skipped_rows(loaded, sequence, rows[-1] if rows else None, row, detections) + [row]
                rows.extend(finished)
            self.folder.save(rows, steps, state.state_dict(), elapsed)
            self.events.ranked(step_index, record)
            self.events.step(steps[-1])
            for row in finished:
                self.events.frame(row)
        summary = self.summary(rows, total // c.steps_per_frame, loaded, settings, sequence, initializer)
        self.folder.write_summary(summary)
        return summary

    def _clock(self, sequence: Sequence) -> Clock:
        """The run's clock (``--clock``), with the frames' timestamps when the sequence has them."""
        c = self.config
        times = [f.time_s for f in sequence.frames]
        observed = None if any(t is None for t in times) else times
        if c.clock == "realtime" and observed is None:
            raise InversionError(f"--clock realtime needs the frames' timestamps and {c.sequence} has none (SHIRT "
                                 "gives them in roeN/metadata.json, pSim.cam_step): give --frame-interval-s SECONDS")
        return Clock(c.clock, len(sequence.frames), observed, c.clock_speed, c.clock_cost_s)

    def _detections(self, sequence: Sequence) -> tuple[list[Detection | None], list[float]]:
        """The object in every frame: from the mask folder when one is given, else found on the dark
        background; and the seconds each detection took (the clock charges a frame's when a step takes it)."""
        if self.config.masks is None:
            return _timed_each(find_object, [f.image for f in sequence.frames])
        height, width = sequence.frames[0].image.shape[:2]
        try:
            masks = read_masks(self.config.masks, [f.name for f in sequence.frames], (height, width))
        except MaskError as err:
            raise InversionError(f"--masks: {err}") from err
        return _timed_each(detection_from_mask, masks)

    def _initializer(self, loaded: LoadedModel, centre: Tensor, settings: RenderSettings,
                     radius: float) -> Initializer:
        """The view bank framing ``radius`` (model units), from the cache or rendered now."""
        initializer = Initializer.create(loaded, settings, centre.numpy().astype(np.float64), self.config.bank,
                                         self.events.bank, radius)
        how = f"rendered in {initializer.build_s:.1f} s" if initializer.built else "read from the cache"
        self.events.info(f"view bank: {self.config.bank.views} views x {self.config.bank.in_plane} in-plane angles, "
                         f"{how} ({initializer.cache})")
        return initializer

    @staticmethod
    def _reanchor(loaded: LoadedModel, settings: RenderSettings, state: TrackerState, frame: Frame,
                  detections: list[Detection | None], k: int, centre: Tensor, radius: float) -> None:
        """``--reanchor``: move the candidates the last step carried (not the bank's that joined since) by the
        camera's motion from the frame they were estimated on to frame ``k``, read off the best one's silhouette
        aligned with both frames' objects (:mod:`nerfinv_plugin.inversion.reanchor`; frames that cut the object
        included). ``radius`` (model units) holds the object about ``centre``."""
        before, after = detections[state.last_frame], detections[k]
        if before is None or after is None:
            return
        anchor = silhouette_anchor(loaded, settings, state.candidates[0], before, after, frame.intrinsics, centre,
                                   radius)
        if anchor is not None:
            carried = state.candidates[:state.carried]
            moved = reanchor(carried, state.candidates[0], centre, anchor, frame.intrinsics)
            state.candidates = torch.cat([moved, state.candidates[state.carried:]])

    def _ask_bank(self, initializer: Initializer, state: TrackerState, frame: Frame, detection: Detection,
                  opacity: np.ndarray | None) -> tuple[bool, int]:
        """Before a frame's first step, ask the bank about it. When the best candidate, whose silhouette is
        ``opacity`` (:func:`rendered_silhouette`; None with the lost check off), no longer puts the
        object where the frame shows it (lost), all of ``reinit_count`` hypotheses join the candidates;
        otherwise the best ``watch_count`` that are more than ``watch_deg`` from every candidate do (a
        wrong mode of a near-symmetric object keeps the silhouette, so only another attitude tells), unless
        the frame cuts the object: the bank matches whole silhouettes and sets the range from the box, so on a
        cut one its hypotheses are wrong in range and attitude alike. Returns (lost, hypotheses added)."""
        c = self.config
        if c.lost_iou > 0:
            iou = silhouette_iou(opacity, detection.mask)
            if iou < c.lost_iou:
                found = initializer.poses(frame.image, detection, frame.intrinsics, c.reinit_count)
                state.candidates = torch.cat([state.candidates, found])
                self.events.warn(f"frame {frame.name}: the object is not where the estimate puts it (silhouette "
                                 f"IoU {iou:.2f}); {len(found)} bank hypotheses join the candidates")
                return True, len(found)
        if c.watch_count == 0 or detection.touches_border:
            return False, 0
        found = initializer.poses(frame.image, detection, frame.intrinsics, c.watch_count)
        apart = attitude_deg(found, state.candidates).min(1).values > c.watch_deg
        state.candidates = torch.cat([state.candidates, found[apart]])
        return False, int(apart.sum())

    def _starts(self, loaded: LoadedModel, sequence: Sequence, centre: Tensor, detections: list[Detection | None],
                initializer: Initializer | None) -> Tensor:
        """Starting candidates [N, 4, 4] in the model frame."""
        s, target = self.config.starts, np.asarray(self.config.target, dtype=np.float64)
        rng = np.random.default_rng(self.config.seed)
        if initializer is not None:
            first = next((k for k, d in enumerate(detections) if d is not None), None)
            if first is None:
                raise InversionError(f"no object found in any of the {len(detections)} frames of "
                                     f"{self.config.sequence} (nothing bright enough on a dark background): give "
                                     "--masks, or check the frames")
            if first > 0:
                self.events.warn(f"no object in the first {first} frame(s); the bank starts from frame {first}")
            frame = sequence.frames[first]
            return initializer.poses(frame.image, detections[first], sequence.intrinsics, s.count)
        first_truth = sequence.frames[0].c2w_true
        if s.source == "truth-offset" or (s.source == "sphere-shell" and s.range_m is None):
            if first_truth is None:
                raise InversionError(f"--starts.source {s.source} (without --starts.range-m) needs the first "
                                     "frame's true pose and this sequence has none: use --starts.source "
                                     "bank, or sphere-shell --starts.range-m METRES")
        if s.source == "truth-offset":
            truth = torch.as_tensor(loaded.dataset_to_model(first_truth), dtype=torch.float32)
            return starts.inerf_protocol_starts(truth, centre, s.count, s.min_deg, s.max_deg,
                                                s.shift_m * loaded.dataparser_scale, self.config.seed)
        if s.source == "sphere-shell":
            radius = s.range_m if s.range_m is not None else float(np.linalg.norm(first_truth[:3, 3] - target))
            poses = starts.sphere_shell(s.count, radius, target, rng)
        elif s.source == "volume":
            poses = starts.volume(s.count, s.max_range_m, s.min_range_m, target, rng)
        elif s.source == "prior":
            if s.prior_q is None or s.prior_r is None:
                raise InversionError("--starts.source prior needs the approximate first pose: --starts.prior-q QW QX "
                                     "QY QZ --starts.prior-r X Y Z (a SHIRT label)")
            prior = opencv_to_opengl(label_to_c2w_opencv(np.asarray(s.prior_q), np.asarray(s.prior_r)))
            poses = starts.around_prior(prior, s.count, s.max_deg, s.shift_m, target, self.config.seed)
        elif s.source == "shirt-labels":
            poses = starts.drawn_from(shirt_label_pool(self.config), s.count, rng)
        elif s.source == "training-views":
            poses = starts.training_views(self._training_transforms(loaded), s.count, rng)
        else:
            assert_never(s.source)
        return torch.as_tensor(loaded.dataset_to_model(poses), dtype=torch.float32)

    @staticmethod
    def _training_transforms(loaded: LoadedModel) -> Path:
        datamanager = loaded.config.pipeline.datamanager
        data = datamanager.data or datamanager.dataparser.data
        for name in ("transforms_train.json", "transforms.json"):
            if data is not None and (Path(data) / name).is_file():
                return Path(data) / name
        raise InversionError(f"training-views starts need the model's training data, but no transforms_train.json "
                             f"or transforms.json is in '{data}' (config.yml's data path, relative to where "
                             "ns-train ran): run from there, or use --starts.source sphere-shell")

    def _frame_number(self, k: int) -> int:
        """Position in the whole sequence of the ``k``-th frame used."""
        return self.config.start + k * self.config.stride

    @staticmethod
    def _step_row(record: StepRecord, index: int, frame: int, step: int, wall: float, reinitialized: bool,
                  watched: int, clock_start_s: float, clock_end_s: float) -> StepRow:
        history = record.result.history
        errors = bool(history) and history[0].error_deg is not None
        return StepRow(
            index=index, frame=frame, step=step, wall_time_s=wall, candidates=record.candidates, kept=record.kept,
            dropped=record.result.dropped, pruned=record.result.pruned, iterations=len(history), loss=record.loss,
            reinitialized=reinitialized, bank_added=watched,
            best_loss_per_iteration=[float(np.min(h.loss)) for h in history], clock_start_s=clock_start_s,
            clock_end_s=clock_end_s,
            best_error_deg_per_iteration=[float(np.min(h.error_deg)) for h in history] if errors else None,
            error_of_best_loss_per_iteration=[float(h.error_deg[np.argmin(h.loss)]) for h in history]
            if errors else None)

    def _frame_row(self, loaded: LoadedModel, record: StepRecord, sequence: Sequence, k: int, wall: float,
                   elapsed: float, object_found: bool, reinitialized: bool, bank_added: int,
                   clock: Clock) -> FrameResult:
        estimate_model = record.estimate.double().numpy()
        q, r = dataset_pose_to_label(loaded.model_to_dataset(estimate_model))
        observed = clock.observed(k)
        row = FrameResult(index=k, frame=self._frame_number(k), name=sequence.frames[k].name,
                          steps=self.config.steps_per_frame, wall_time_s=wall, elapsed_s=elapsed, q=q, r=r,
                          c2w_model=estimate_model.tolist(), loss=record.loss, outline_loss=record.outline_loss,
                          silhouette_weight=record.silhouette_weight, candidates=record.candidates,
                          dropped=len(record.result.dropped), object_found=object_found, reinitialized=reinitialized,
                          bank_added=bank_added, observed_s=observed, estimated_s=clock.now_s,
                          latency_s=None if observed is None else clock.now_s - observed)
        return self._with_errors(row, sequence)

    def _with_errors(self, row: FrameResult, sequence: Sequence) -> FrameResult:
        """``row`` with its errors against the frame's true pose, when known."""
        truth = sequence.frames[row.index].c2w_true
        if truth is None:
            return row
        q_true, r_true = dataset_pose_to_label(truth)
        error = label_error(np.array(row.q), np.array(row.r), np.array(q_true), np.array(r_true),
                            hil="lightbox" in str(self.config.sequence))
        return dataclasses.replace(row, rotation_deg=error.rotation_deg, translation_m=error.translation_m,
                                   translation_rel=error.translation_rel, score=error.score)

    def _skipped_rows(self, loaded: LoadedModel, sequence: Sequence, before: FrameResult | None, after: FrameResult,
                      detections: list[Detection | None]) -> list[FrameResult]:
        """The frames between the estimated ``before`` and ``after`` that the realtime clock skipped, with
        poses interpolated on SE(3) between theirs at their observation times; known once ``after`` is."""
        if before is None or after.index == before.index + 1:
            return []
        a, b = torch.as_tensor(before.c2w_model), torch.as_tensor(after.c2w_model)
        rows = []
        for j in range(before.index + 1, after.index):
            observed = sequence.frames[j].time_s
            pose = interpolated_pose(a, b, fraction_between(before.observed_s, observed, after.observed_s)).numpy()
            q, r = dataset_pose_to_label(loaded.model_to_dataset(pose))
            row = FrameResult(index=j, frame=self._frame_number(j), name=sequence.frames[j].name, steps=0,
                              wall_time_s=0.0, elapsed_s=after.elapsed_s, q=q, r=r, c2w_model=pose.tolist(), loss=None,
                              candidates=0, dropped=0, object_found=detections[j] is not None, interpolated=True,
                              observed_s=observed, estimated_s=after.estimated_s,
                              latency_s=after.estimated_s - observed)
            rows.append(self._with_errors(row, sequence))
        return rows

    def summary(self, rows: list[FrameResult], total_frames: int, loaded: LoadedModel, settings: RenderSettings,
                sequence: Sequence, initializer: Initializer | None = None) -> RunSummary:
        bank = None
        if initializer is not None:
            bank = BankSummary(views=self.config.bank.views, entries=len(initializer.entries.views),
                               built_in_this_run=initializer.built, render_s=initializer.build_s,
                               cache=str(initializer.cache))
        return dataclasses.replace(
            summarize(rows), run=str(self.folder.path), model=str(self.config.load_config), model_step=loaded.step,
            sequence=str(self.config.sequence), sequence_format=sequence.kind, frames_total=total_frames,
            complete=len(rows) == total_frames, device=str(loaded.device), starts=self.config.starts.source,
            frames_without_object=sum(not r.object_found for r in rows),
            frames_reinitialized=sum(bool(r.reinitialized) for r in rows), clock=self.config.clock,
            target_radius_m=None if settings.target_sphere is None else
            float(settings.target_sphere[1]) / loaded.dataparser_scale,
            bank=bank)
