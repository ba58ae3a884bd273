"""``ns-invert``: estimate the pose in every frame of a sequence with a trained nerfstudio model."""

import sys
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from nerfinv_plugin.cli import Interrupted, run
from nerfinv_plugin.data.sequences import SequenceError
from nerfinv_plugin.inversion.optimizer import IterationRecord
from nerfinv_plugin.inversion.session import Events, Inversion, InversionError
from nerfinv_plugin.inversion.settings import InvertConfig, SettingsError, defaults_with_preset
from nerfinv_plugin.inversion.validation import validate
from nerfinv_plugin.model.loaded import ModelLoadError
from nerfinv_plugin.report.build import write_report
from nerfinv_plugin.results.records import FrameResult, RunSummary, StepRow
from nerfinv_plugin.results.summary import LOCK_DEG
from nerfinv_plugin.viewer.live import LiveViewer, start_server, viewer_url
from nerfinv_plugin.viewer.record import TrailRecorder, merged

BAD_INPUT = (ModelLoadError, SequenceError, SettingsError, InversionError, FloatingPointError)
"""Errors that mean the input or the settings are wrong: one line and exit code 2, no traceback."""


def _frame_line(row: FrameResult) -> str:
    error = "" if row.rotation_deg is None else \
        f"rotation {row.rotation_deg:.2f} deg, translation {row.translation_m:.3f} m, "
    latency = "" if row.latency_s is None else f", latency {row.latency_s:.1f} s"
    if row.interpolated:
        return f"frame {row.frame} ({row.name}): skipped, pose interpolated; {error}{latency.removeprefix(', ')}"
    flags = "" if row.object_found else ", no object found"
    flags += ", bank asked again" if row.reinitialized else \
        (f", {row.bank_added} bank hypotheses joined" if row.bank_added else "")
    return (f"frame {row.frame} ({row.name}): {error}loss {row.loss:.5f}, {row.candidates} candidates, "
            f"{row.wall_time_s:.1f} s{latency}{flags}")


def _summary_lines(summary: RunSummary) -> list[str]:
    wall = 0.0 if summary.wall_time_s is None else summary.wall_time_s
    per_frame = 0.0 if summary.mean_time_per_frame_s is None else summary.mean_time_per_frame_s
    lines = [f"{summary.frames_done} of {summary.frames_total} frames in {wall:.0f} s ({per_frame:.1f} s a frame)"]
    if summary.rotation_deg is not None:
        rot, success = summary.rotation_deg, summary.success_rotation
        lines.append(f"rotation error mean {rot.mean:.2f} deg, median {rot.median:.2f}, final "
                     f"{rot.final:.2f}; under 2/5/10 deg: " +
                     " / ".join(f"{100 * v:.0f}%" for v in success.values()))
        lines.append(f"translation error mean {summary.translation_m.mean:.3f} m "
                     f"({100 * summary.translation_rel.mean:.1f}% of range); "
                     f"SPEC score mean {summary.score.mean:.4f}")
    lines += _clock_lines(summary)
    return lines


def _clock_lines(summary: RunSummary) -> list[str]:
    """Latency, frames skipped and the first lock; the accuracy over the estimated frames alone."""
    lines = []
    if summary.latency_s is not None:
        latency = summary.latency_s
        lines.append(f"latency (observation to estimate, clock {summary.clock}) mean {latency.mean:.2f} s, median "
                     f"{latency.median:.2f}, max {latency.max:.2f}; {summary.frames_skipped} of {summary.frames_done} "
                     "frames skipped (interpolated)")
    if summary.rotation_deg is not None:
        lock = "never" if summary.time_to_first_lock_s is None else \
            f"{summary.time_to_first_lock_s:.1f} s (frame {summary.first_lock_frame})"
        lines.append(f"first estimate under {LOCK_DEG:g} deg: {lock}")
    estimated = summary.estimated_only
    if estimated is not None:
        lines.append(f"over the {estimated.frames} estimated frames alone: rotation error mean "
                     f"{estimated.rotation_deg.mean:.2f} deg, median {estimated.rotation_deg.median:.2f}; under "
                     "2/5/10 deg: " + " / ".join(f"{100 * v:.0f}%" for v in estimated.success_rotation.values()))
    return lines


def invert(config: InvertConfig, console: Console, viewer: LiveViewer | None = None) -> RunSummary:
    """Run with a rich progress bar (loss and error of the best candidate) and one line per frame,
    recording the candidate trail in the run folder, and drawing the run on ``viewer`` when given."""
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("loss {task.fields[loss]}  error {task.fields[error]}"))
    with Progress(*columns, console=console) as progress:
        task = progress.add_task("loading", total=None, loss="-", error="-")
        steps, iterations_per_step = 0, 0

        def begin(total_steps: int, done_steps: int, per_step: int) -> None:
            nonlocal steps, iterations_per_step
            steps, iterations_per_step = total_steps, per_step
            console.print(f"results: {inversion.folder.path}")
            progress.update(task, total=total_steps * per_step, completed=done_steps * per_step,
                            description=f"step {done_steps + 1}/{total_steps}")

        def iteration(i: int, record: IterationRecord) -> None:
            best = int(np.argmin(record.loss))
            error = "-" if record.error_deg is None else f"{record.error_deg[best]:.2f} deg"
            progress.update(task, advance=1, loss=f"{record.loss[best]:.5f}", error=error)

        def step(row: StepRow) -> None:
            progress.update(task, description=f"step {min(row.step + 2, steps)}/{steps}")

        def bank(views: int) -> Callable[[int], None]:
            bank_task = progress.add_task("view bank", total=views, loss="-", error="-")
            return lambda done: progress.update(bank_task, advance=done)

        def frame(row: FrameResult) -> None:
            # Frames the realtime clock skipped, and steps that stopped early, run fewer iterations than the
            # bar's total counts: a finished frame moves the bar to its share of the total.
            progress.update(task, completed=(row.index + 1) * iterations_per_step * inversion.config.steps_per_frame)
            console.print(_frame_line(row))

        events = Events(begin, iteration, step, frame,
                        lambda message: console.print(f"[yellow]{escape(message)}[/yellow]"),
                        lambda message: console.print(escape(message)), bank)
        inversion = Inversion.resume(config.resume, events) if config.resume else Inversion.create(config, events)
        drawn = [] if viewer is None else [viewer.events()]
        inversion.events = merged(events, TrailRecorder(inversion.folder.path).events(), *drawn)
        try:
            summary = inversion.run()
        except KeyboardInterrupt:
            raise Interrupted(f"interrupted; every finished frame is saved in {inversion.folder.path}. "
                              f"Continue with: ns-invert --resume {inversion.folder.path}") from None
    for line in _summary_lines(summary):
        console.print(f"[bold]{line}[/bold]")
    page = write_report(inversion.folder.path, overlays=True, device=inversion.config.device,
                        warn=lambda message: console.print(f"[yellow]{escape(message)}[/yellow]"))
    console.print(f"report: {page}")
    return summary


@dataclass
class Invert(InvertConfig):
    __doc__ = InvertConfig.__doc__

    def main(self) -> None:
        validate(self)  # before anything is loaded or written
        if not self.viewer:
            invert(self, Console())
            return
        console, server = Console(), start_server(self.viewer_port)
        console.print(viewer_url(server))
        try:
            invert(self, console, LiveViewer(server, self.viewer_render))
        finally:
            server.stop()


def entrypoint() -> None:
    try:
        preset = defaults_with_preset()
    except SettingsError as err:
        Console(stderr=True, soft_wrap=True).print(f"[red]ns-invert: {escape(str(err))}[/red]")
        sys.exit(2)
    run(Invert, "ns-invert", *BAD_INPUT, default=Invert(**{f.name: getattr(preset, f.name) for f in fields(preset)}))


if __name__ == "__main__":
    entrypoint()
