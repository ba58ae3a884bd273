"""A run's report: figures in ``<run>/report/`` and ``<run>/report.html`` beside the results files.

Everything but two figures comes from the run folder alone. The overlay and the filmstrip render the
model at the estimates, so they also need the trained model and the sequence where config.yml says they
are; when either is gone the rest is still written, and the page says what is missing and why. A figure
that needs ground truth is left out (never drawn empty) on a sequence without it.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from nerfinv_plugin.data.sequences import SequenceError, SequenceFrame, read_sequence
from nerfinv_plugin.inversion.settings import InvertConfig, SettingsError, read_config
from nerfinv_plugin.model.loaded import LoadedModel, ModelLoadError
from nerfinv_plugin.model.loading import Device, load_model
from nerfinv_plugin.model.render import Intrinsics, render_image
from nerfinv_plugin.report import figures
from nerfinv_plugin.report.html import Page, Part, render
from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.results.folder import CONFIG, RESULTS_JSONL, RunFolder
from nerfinv_plugin.results.records import FrameResult, RunSummary, StepRow
from nerfinv_plugin.results.summary import summarize

REPORT_DIR = "report"
REPORT_HTML = "report.html"
OVERLAY_FRAMES = 3
"""Default overlay: the first, middle and last frame."""
FILMSTRIP_FRAMES = 8


class ReportError(Exception):
    """A folder that is not a run, or frames the run does not have; the message says what to give instead."""


@dataclass(frozen=True)
class Plan:
    """A figure's file name (under ``report/``), heading and caption."""

    name: str
    title: str
    caption: str


ERROR_VS_TIME = Plan(
    "error_vs_time.png", "Error against time",
    "Rotation error of the estimate after every Monte Carlo step against the run's wall time (thesis fig. "
    "5.2). Filled markers are the poses reported for frames; the gaps between markers are what each step "
    "cost, which shrinks as fewer candidates survive. Dashed lines: 2, 5 and 10 degrees.")
LATENCY = Plan(
    "latency_vs_time.png", "Latency (observation to estimate)",
    "Every frame at the time it was observed on the run's clock (--clock): the rotation error of its pose "
    "(with ground truth) and its latency, from observation to estimate. Filled markers: frames a Monte Carlo "
    "step estimated; open: frames the realtime clock skipped, their poses interpolated on SE(3) between "
    "their neighbours' (known once the later one is). Dashed: the time between frames (a latency under it "
    "keeps up with the camera); dotted: the first estimate under 5 degrees.")
ITERATIONS = Plan(
    "loss_error_per_iteration.png", "Loss and error at every iteration",
    "The lowest loss among the candidates at every gradient iteration, all Monte Carlo steps one after "
    "the other, and (with ground truth) the rotation error of the lowest-loss candidate and the lowest "
    "error of any candidate. Grey lines mark resampling; a gap between the two error curves means the loss "
    "ranks a worse candidate first.")
PER_FRAME = Plan(
    "error_per_frame.png", "Error in each frame",
    "Rotation error (top) and translation error (bottom) of the pose reported for each frame of the "
    "sequence: flat and low while tracking holds; a jump marks where the target was lost.")
OVERLAY = Plan(
    "overlays.png", "Estimate over the observed image",
    "For a few frames: the observed image, the model rendered at the estimated pose, the two blended "
    "(thesis fig. 5.1: the observed image is the faint one) and their absolute difference (bright: "
    "disagreement).")
FILMSTRIP = Plan(
    "filmstrip.png", "Filmstrip",
    "Frames spread over the run: observed (top) and the model rendered at each frame's estimate (bottom), "
    "as in thesis fig. 5.5.")


@dataclass
class Run:
    """What a run folder holds, read once."""

    path: Path
    rows: list[FrameResult]
    steps: list[StepRow]
    summary: RunSummary
    """``summarize(rows)`` over the rows now, with summary.json's fields about the run (total frames,
    model step, device) where the run wrote it."""
    settings: str
    """config.yml's text, or why it cannot be shown."""
    config: InvertConfig | None
    config_problem: str = ""
    """Why ``config`` is ``None``."""


@dataclass
class Renderer:
    """The model and the sequence, loaded once for both image figures; each frame is rendered once."""

    loaded: LoadedModel
    frames: list[SequenceFrame]
    intrinsics: Intrinsics
    cache: dict[int, figures.View] = field(default_factory=dict)

    @classmethod
    def open(cls, config: InvertConfig, device: Device) -> "Renderer":
        loaded = load_model(config.load_config, device=device)
        sequence = read_sequence(config.sequence, config.start, config.stop, config.stride, config.resolution,
                                 config.camera)
        return cls(loaded, sequence.frames, sequence.intrinsics)

    def view(self, row: FrameResult) -> figures.View:
        """Checks that the frame on disk is still the one the run saw: an estimate over another image
        would look like a failure of the method."""
        k = row.index
        if k not in self.cache:
            if k >= len(self.frames) or self.frames[k].name != row.name:
                found = self.frames[k].name if k < len(self.frames) else "missing"
                raise SequenceError(f"frame {row.frame} of the sequence is now {found}, but the run used "
                                    f"{row.name}: the data changed since the run")
            rendered = render_image(self.loaded, np.asarray(row.c2w_model), self.intrinsics)
            self.cache[k] = figures.View(_label(row), self.frames[k].image / 255.0, rendered)
        return self.cache[k]


def _label(row: FrameResult) -> str:
    if row.rotation_deg is None:
        return f"frame {row.frame}"
    return f"frame {row.frame}\n{row.rotation_deg:.1f}°, {row.translation_m:.2f} m"


def read_run(run_dir: Path) -> Run:
    path = Path(run_dir)
    if not (path / RESULTS_JSONL).is_file():
        raise ReportError(f"{path} is not an ns-invert run folder (no {RESULTS_JSONL}); give the folder "
                          "ns-invert printed after 'results:' (outputs/<name>/nerfinv/<timestamp>)")
    folder = RunFolder(path)
    rows = folder.rows()
    stored = folder.summary()  # None while the run is going on or after it was interrupted
    summary = summarize(rows) if stored is None else stored.updated(summarize(rows))
    return Run(path, rows, folder.steps(), summary, *_settings(path / CONFIG))


def _settings(path: Path) -> tuple[str, InvertConfig | None, str]:
    """config.yml's text, the settings read from it, and why they could not be read."""
    try:
        text = path.read_text()
    except OSError:
        problem = f"{CONFIG} is missing from the run folder"
        return problem, None, problem
    try:
        return text, read_config(path), ""
    except SettingsError as err:
        return text, None, str(err)


def _positions(rows: list[FrameResult], frames: Sequence[int] | None) -> list[int]:
    """Positions in ``rows`` of the frames (sequence frame numbers) to overlay."""
    if frames is None:
        return figures.evenly_spaced(len(rows), OVERLAY_FRAMES)
    where = {r.frame: i for i, r in enumerate(rows)}
    unknown = [f for f in frames if f not in where]
    if unknown:
        done = f"{rows[0].frame}..{rows[-1].frame}" if rows else "none yet"
        raise ReportError(f"frame(s) {', '.join(map(str, unknown))} not in this run (frames done: {done}); "
                          "give frame numbers from results.jsonl's 'frame'")
    return [where[f] for f in frames]


def _part(out: Path, plan: Plan, figure: Figure | None, missing: str) -> Part:
    """Save ``figure``, or remove an older report's file of it, so the folder matches the page."""
    target = out / plan.name
    if figure is None:
        target.unlink(missing_ok=True)
        return Part(f"{REPORT_DIR}/{plan.name}", plan.title, plan.caption, missing)
    figures.save(figure, target)
    return Part(f"{REPORT_DIR}/{plan.name}", plan.title, plan.caption)


def _plot_parts(out: Path, run: Run) -> list[Part]:
    no_truth = "the sequence has no ground truth for these frames, so there is no error to plot"
    no_steps = "no Monte Carlo step has finished yet"
    no_frames = "no frame has finished yet"
    parts = [
        _part(out, ERROR_VS_TIME, figures.error_vs_time(run.rows, run.steps), no_truth if run.steps else no_steps),
        _part(out, ITERATIONS, figures.loss_and_error_per_iteration(run.steps), no_steps),
        _part(out, PER_FRAME, figures.per_frame_errors(run.rows), no_truth if run.rows else no_frames),
    ]
    # Latency is observation to estimate: a sequence without timestamps (a Blender split, an image folder
    # without --frame-interval-s) has none, and the page leaves the figure out rather than calling it missing.
    if not run.rows or any(r.observed_s is not None for r in run.rows):
        latency = figures.latency_vs_time(run.rows, _frame_interval(run.rows), run.summary.time_to_first_lock_s)
        no_times = "the sequence has no timestamps (SHIRT's metadata.json, or ns-invert --frame-interval-s)"
        parts.insert(1, _part(out, LATENCY, latency, no_times if run.rows else no_frames))
    else:
        (out / LATENCY.name).unlink(missing_ok=True)
    return parts


def _frame_interval(rows: list[FrameResult]) -> float | None:
    """Seconds between the run's consecutive frames, read off their observation times."""
    times = np.array([r.observed_s for r in rows if r.observed_s is not None], float)
    return float(np.diff(times).min()) if times.size > 1 else None


def _why_no_images(run: Run, overlays: bool) -> str:
    if not overlays:
        return "rendering was turned off (--no-overlays)"
    if not run.rows:
        return "no frame has finished yet"
    if run.config is None:
        return f"{run.config_problem}; without the run's settings the model and the sequence cannot be found"
    return ""


def _image_parts(out: Path, run: Run, overlays: bool, device: Device, positions: list[int]) -> list[Part]:
    missing = _why_no_images(run, overlays)
    if not missing:
        try:
            renderer = Renderer.open(run.config, device)
            chosen = [renderer.view(run.rows[i]) for i in positions]
            strip = [renderer.view(run.rows[i]) for i in figures.evenly_spaced(len(run.rows), FILMSTRIP_FRAMES)]
        except (ModelLoadError, SequenceError, OSError) as err:
            missing = (f"rendering the estimates needs the run's model and sequence: {err}. Put them back (or "
                       f"correct load_config and sequence in {CONFIG}), then run ns-invert-report {run.path}")
    if missing:
        return [_part(out, OVERLAY, None, missing), _part(out, FILMSTRIP, None, missing)]
    return [_part(out, OVERLAY, figures.overlays(chosen), ""), _part(out, FILMSTRIP, figures.filmstrip(strip), "")]


def _title(path: Path) -> str:
    name = path.parent.parent.name if path.parent.name == "nerfinv" else path.parent.name
    return f"ns-invert run {name} / {path.name}"


def _meta(run: Run) -> list[tuple[str, str]]:
    s, c = run.summary, run.config
    lines = [("run folder", str(run.path))]
    if c is not None:
        step = "" if s.model_step is None else f" (step {s.model_step})"
        frames = f"frames {c.start}:{'' if c.stop is None else c.stop}:{c.stride}"
        lines += [("model", f"{c.load_config}{step}"), ("sequence", f"{c.sequence}, {frames}")]
    if s.device is not None:
        lines.append(("device", s.device))
    lines.append(("report written", datetime.now().strftime("%Y-%m-%d %H:%M:%S")))
    return lines


def _warn_missing(parts: list[Part], warn: Callable[[str], None]) -> None:
    """One message per reason: the overlay and the filmstrip are missing for the same one."""
    titles: dict[str, list[str]] = {}
    for part in parts:
        if part.missing:
            titles.setdefault(part.missing, []).append(part.title.lower())
    for reason, names in titles.items():
        warn(f"left out {' and '.join(names)}: {reason}")


def write_report(run_dir: Path, overlays: bool = True, device: Device = "cpu", frames: Sequence[int] | None = None,
                 warn: Callable[[str], None] = lambda message: None) -> Path:
    """Write ``report.html`` and its figures into the run folder ``run_dir``; return the page's path.
    ``overlays`` renders the model for the overlay and filmstrip figures (on ``device``), at ``frames``
    (sequence frame numbers; default first, middle and last). ``warn`` hears about each figure left out."""
    run = read_run(run_dir)
    positions = _positions(run.rows, frames)
    out = run.path / REPORT_DIR
    out.mkdir(exist_ok=True)
    parts = _plot_parts(out, run) + _image_parts(out, run, overlays, device, positions)
    _warn_missing(parts, warn)
    page = Page(_title(run.path), _meta(run), run.summary, run.rows, parts, run.settings)
    write_atomic(run.path / REPORT_HTML, render(page))
    return run.path / REPORT_HTML
