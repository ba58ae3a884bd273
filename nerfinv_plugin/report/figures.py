"""The figures of a run's report (thesis chapter 5): how the error falls with time and iterations, the
error of every frame, and the estimate drawn beside and over the observed image.

Figures are built on matplotlib's object API with an Agg canvas rather than pyplot: no global figure
state to leak between reports, no display needed, nothing to close afterwards.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from nerfinv_plugin.results.records import FrameResult, StepRow
from nerfinv_plugin.results.summary import SUCCESS_DEG

DPI = 120
THRESHOLD_COLOURS = ("tab:green", "goldenrod", "tab:red")
"""One per threshold of ``SUCCESS_DEG``: the colours go from good to bad."""
OBSERVED_WEIGHT = 0.35
"""Share of the observed image in the overlay; the estimate gets the rest (thesis fig. 5.1: the observed
image is the faint one)."""
DIFFERENCE_MAX = 0.5
"""Colour-scale top of the difference image: most misalignments stay under it, and a fixed scale lets
frames be compared with each other."""
PANEL_INCHES = 2.4
"""Width of one image panel."""


@dataclass(frozen=True)
class StepPoints:
    """The estimate's error at the end of every Monte Carlo step whose error is known."""

    time_s: np.ndarray
    """Run time (wall clock, cumulative over steps) when the step ended."""
    error_deg: np.ndarray
    ends_frame: np.ndarray
    """True where the step's estimate is the frame's result (its error is the one in results.jsonl)."""
    candidates: np.ndarray


@dataclass(frozen=True)
class View:
    """One frame as observed and as the model renders it at the estimate, both [H, W, 3] in [0, 1]."""

    label: str
    observed: np.ndarray
    rendered: np.ndarray


def save(figure: Figure, path: Path) -> None:
    FigureCanvasAgg(figure)
    figure.savefig(path, dpi=DPI)


def evenly_spaced(count: int, wanted: int) -> list[int]:
    """Up to ``wanted`` positions spread over ``range(count)``, always with the first and the last."""
    if count <= 0 or wanted <= 0:
        return []
    return sorted({int(i) for i in np.linspace(0, count - 1, min(count, wanted)).round()})


def step_points(rows: list[FrameResult], steps: list[StepRow]) -> StepPoints:
    """A step that ends a frame takes the frame's error from ``rows`` (the error of the pose reported for
    it); any other step, that of its lowest-loss candidate after its last iteration. Steps without a
    known error are left out, but their time still counts."""
    last_step = {s.index: s.step for s in steps}
    by_index = {r.index: r for r in rows}
    clock = np.cumsum([s.wall_time_s for s in steps])
    points = []
    for step, time_s in zip(steps, clock):
        row = by_index.get(step.index) if last_step[step.index] == step.step else None
        history = step.error_of_best_loss_per_iteration or [None]
        error = row.rotation_deg if row is not None else history[-1]
        if error is not None:
            points.append((time_s, error, row is not None, step.candidates))
    time_s, error, ends, candidates = zip(*points) if points else ((), (), (), ())
    return StepPoints(np.array(time_s, float), np.array(error, float), np.array(ends, bool),
                      np.array(candidates, int))


def _figure(width: float, height: float, rows: int = 1, sharex: bool = False) -> tuple[Figure, list[Axes]]:
    figure = Figure(figsize=(width, height), layout="constrained")
    axes = figure.subplots(rows, 1, sharex=sharex, squeeze=False)[:, 0]
    for ax in axes:
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
    return figure, list(axes)


def _log_if_wide(ax: Axes, values: np.ndarray) -> None:
    """Log scale when the values span more than a decade, else the small end is a flat line at zero."""
    positive = values[np.isfinite(values) & (values > 0)]
    if positive.size and positive.max() > 10 * positive.min():
        ax.set_yscale("log")


def _legend(ax: Axes) -> None:
    """Beside the axes: inside, it hides the points it explains."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0, fontsize=8)


def _thresholds(ax: Axes) -> None:
    for threshold, colour in zip(SUCCESS_DEG, THRESHOLD_COLOURS):
        ax.axhline(threshold, ls="--", lw=1, color=colour, label=f"{threshold:g}°")


def _label_candidates(ax: Axes, points: StepPoints) -> None:
    """Name the candidate count at the first step that has it: once per count, so a run that starts
    every frame afresh (fixed mode) is not covered in labels. Labels near the right end go to the left."""
    _, first = np.unique(points.candidates, return_index=True)
    right = points.time_s.max()
    for i in first:
        left = points.time_s[i] > 0.7 * right
        ax.annotate(f"{points.candidates[i]} candidates", (points.time_s[i], points.error_deg[i]),
                    textcoords="offset points", xytext=(-4 if left else 4, 7), ha="right" if left else "left",
                    fontsize=8, color="0.3")


def error_vs_time(rows: list[FrameResult], steps: list[StepRow]) -> Figure | None:
    """Thesis fig. 5.2: one marker per Monte Carlo step. The spacing of the markers shows how much a step
    costs, which shrinks as fewer candidates survive; the candidate count is written where it changes."""
    points = step_points(rows, steps)
    if not points.time_s.size:
        return None
    figure, (ax,) = _figure(9.5, 4.5)
    ax.plot(points.time_s, points.error_deg, "-", color="tab:blue", lw=1.2, alpha=0.5)
    ends = points.ends_frame
    ax.plot(points.time_s[ends], points.error_deg[ends], "o", color="tab:blue", ms=5,
            label="step that ends a frame (the frame's estimate)")
    if not ends.all():
        ax.plot(points.time_s[~ends], points.error_deg[~ends], "o", color="tab:blue", mfc="white", ms=5,
                label="step within a frame (its lowest-loss candidate)")
    _label_candidates(ax, points)
    ax.margins(x=0.04, y=0.12)  # room for the labels
    _log_if_wide(ax, points.error_deg)
    _thresholds(ax)
    ax.set_xlim(left=0)
    ax.set(xlabel="wall time since the run started (s)", ylabel="rotation error (deg)",
           title="Rotation error of the estimate after each Monte Carlo step")
    _legend(ax)
    return figure


def latency_vs_time(rows: list[FrameResult], frame_interval_s: float | None = None,
                    first_lock_s: float | None = None) -> Figure | None:
    """Error and latency against the run's clock (thesis fig. 5.2 on the camera's time): one marker per
    frame at the time it was observed, filled where a step estimated it, open where the realtime clock
    skipped it and its pose is interpolated. The latency panel has the frame interval as a line (a solver
    under it keeps up with the camera); the first estimate under 5 degrees is marked in both."""
    timed = [r for r in rows if r.observed_s is not None and r.latency_s is not None]
    if not timed:
        return None
    with_error = any(r.rotation_deg is not None for r in timed)
    figure, axes = _figure(9.5, 6.0 if with_error else 3.4, rows=2 if with_error else 1, sharex=True)
    observed = np.array([r.observed_s for r in timed], float)
    skipped = np.array([r.interpolated for r in timed], bool)
    panels = [("rotation error (deg)", np.array([np.nan if r.rotation_deg is None else r.rotation_deg
                                                 for r in timed], float), "tab:blue")] if with_error else []
    panels.append(("latency (s)", np.array([r.latency_s for r in timed], float), "tab:purple"))
    for ax, (label, values, colour) in zip(axes, panels):
        ax.plot(observed, values, "-", color=colour, lw=1.0, alpha=0.4)
        ax.plot(observed[~skipped], values[~skipped], "o", color=colour, ms=5, label="estimated by a step")
        if skipped.any():
            ax.plot(observed[skipped], values[skipped], "o", color=colour, mfc="white", ms=5,
                    label="skipped: pose interpolated")
        if first_lock_s is not None:
            ax.axvline(first_lock_s, color="tab:green", lw=1, ls=":", label=f"first under 5° ({first_lock_s:.0f} s)")
        ax.set(ylabel=label)
    if with_error:
        _log_if_wide(axes[0], panels[0][1])
        _thresholds(axes[0])
        axes[0].set(title="Error and latency of every frame against the run's clock")
    else:
        axes[0].set(title="Latency of every frame against the run's clock")
    if frame_interval_s is not None:
        axes[-1].axhline(frame_interval_s, color="0.4", ls="--", lw=1, label=f"frame interval ({frame_interval_s:g} s)")
    axes[-1].set_ylim(bottom=0)
    axes[-1].set(xlabel="time the frame was observed (s after the first frame, on the run's clock)")
    for ax in axes:
        _legend(ax)
    return figure


def _concatenated(steps: list[StepRow], history: Callable[[StepRow], list[float] | None]) -> np.ndarray:
    """A per-iteration history over all steps; NaN where a step has none (frames without truth)."""
    return np.concatenate([np.asarray(history(s) or np.full(len(s.best_loss_per_iteration), np.nan), float)
                           for s in steps])


def loss_and_error_per_iteration(steps: list[StepRow]) -> Figure | None:
    """Thesis fig. 5.3 over a whole run: the best loss at every iteration and, with ground truth, the
    error. Step boundaries are where resampling happens (and the learning rate resets)."""
    loss = _concatenated(steps, lambda s: s.best_loss_per_iteration) if steps else np.array([])
    if not loss.size:
        return None
    best_error = _concatenated(steps, lambda s: s.best_error_deg_per_iteration)
    chosen_error = _concatenated(steps, lambda s: s.error_of_best_loss_per_iteration)
    with_error = bool(np.isfinite(chosen_error).any())
    figure, axes = _figure(10.0, 6.0 if with_error else 3.6, rows=2 if with_error else 1, sharex=True)
    iteration = np.arange(1, loss.size + 1)
    axes[0].plot(iteration, loss, color="tab:purple", lw=1.2, label="lowest loss among the candidates")
    _log_if_wide(axes[0], loss)
    axes[0].set(ylabel="loss (sampled pixels)",
                title="Loss" + (" and rotation error" if with_error else "") + " at every iteration")
    if with_error:
        axes[1].plot(iteration, chosen_error, color="tab:blue", lw=1.2, label="error of the lowest-loss candidate")
        axes[1].plot(iteration, best_error, color="tab:cyan", lw=1, ls=":", label="lowest error among the candidates")
        _log_if_wide(axes[1], np.concatenate([chosen_error, best_error]))
        _thresholds(axes[1])
        axes[1].set(ylabel="rotation error (deg)")
    boundaries = np.cumsum([len(s.best_loss_per_iteration) for s in steps])[:-1] + 0.5
    for ax in axes:
        for k, x in enumerate(boundaries):
            ax.axvline(x, color="0.55", lw=0.7, alpha=0.6, label="Monte Carlo step boundary" if k == 0 else None)
        _legend(ax)
    axes[-1].set(xlabel="iteration (all Monte Carlo steps one after the other)", xlim=(0.5, loss.size + 0.5))
    return figure


def per_frame_errors(rows: list[FrameResult]) -> Figure | None:
    """The error of the pose reported for each frame: whether tracking holds, and where it is lost."""
    truth = [r for r in rows if r.rotation_deg is not None]
    if not truth:
        return None
    frame = np.array([r.frame for r in truth])
    rotation = np.array([r.rotation_deg for r in truth], float)
    translation = np.array([r.translation_m for r in truth], float)
    figure, (top, bottom) = _figure(9.5, 5.5, rows=2, sharex=True)
    top.plot(frame, rotation, "o-", color="tab:blue", ms=4, lw=1.2, label="rotation error")
    _log_if_wide(top, rotation)
    _thresholds(top)
    top.set(ylabel="rotation error (deg)", title="Error of the estimate in each frame")
    _legend(top)
    bottom.plot(frame, translation, "o-", color="tab:orange", ms=4, lw=1.2, label="translation error")
    _log_if_wide(bottom, translation)
    bottom.set(xlabel="frame (index in the sequence)", ylabel="translation error (m)")
    _legend(bottom)
    return figure


def _image_axes(figure: Figure, rows: int, cols: int) -> np.ndarray:
    axes = figure.subplots(rows, cols, squeeze=False)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    return axes


def _panel_height(view: View) -> float:
    height, width = view.observed.shape[:2]
    return PANEL_INCHES * height / width


def overlays(views: Sequence[View]) -> Figure:
    """Thesis fig. 5.1 for a few frames: observed, rendered at the estimate, the two blended, and their
    difference, which shows a misalignment that a blend can hide."""
    height = max(3.2, len(views) * (_panel_height(views[0]) + 0.3) + 0.6)  # room for the colour bar's label
    figure = Figure(figsize=(4 * PANEL_INCHES + 1.6, height),
                    layout="constrained")
    axes = _image_axes(figure, len(views), 4)
    titles = ("observed", "rendered at the estimate", f"overlay (observed {OBSERVED_WEIGHT:.0%})",
              "|observed − rendered|")
    for row, view in zip(axes, views):
        blend = OBSERVED_WEIGHT * view.observed + (1 - OBSERVED_WEIGHT) * view.rendered
        difference = np.abs(view.observed - view.rendered).mean(axis=-1)
        for ax, image in zip(row[:3], (view.observed, view.rendered, blend)):
            ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
        shown = row[3].imshow(difference, cmap="inferno", vmin=0, vmax=DIFFERENCE_MAX, interpolation="nearest")
        row[0].set_ylabel(view.label, fontsize=9)
    for ax, title in zip(axes[0], titles):
        ax.set_title(title, fontsize=10)
    figure.colorbar(shown, ax=axes[:, 3], shrink=0.8, label="mean over RGB (0-1)")
    figure.suptitle("Estimated pose against the observed image")
    return figure


def filmstrip(views: Sequence[View]) -> Figure:
    """Thesis fig. 5.5: observed frames on top, the model rendered at each frame's estimate below."""
    width = max(6.0, len(views) * PANEL_INCHES * 0.8 + 0.8)  # room for the title with few frames
    figure = Figure(figsize=(width, 2 * _panel_height(views[0]) * 0.8 + 1.2),
                    layout="constrained")
    axes = _image_axes(figure, 2, len(views))
    for column, view in zip(axes.T, views):
        column[0].imshow(view.observed, interpolation="nearest")
        column[1].imshow(np.clip(view.rendered, 0, 1), interpolation="nearest")
        column[0].set_title(view.label, fontsize=8)
    axes[0, 0].set_ylabel("observed")
    axes[1, 0].set_ylabel("estimate")
    figure.suptitle("Observed frames (top) and the model at each frame's estimate (bottom)", fontsize=11)
    return figure
