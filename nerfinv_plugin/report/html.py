"""``report.html``: one self-contained page per run (inline CSS, no scripts, figures beside it by relative
path), so that it opens from disk, survives the run folder being copied, and needs no server."""

import html
from collections.abc import Iterable
from dataclasses import dataclass

from nerfinv_plugin.results.records import Accuracy, FrameResult, RunSummary
from nerfinv_plugin.results.summary import LOCK_DEG, SUCCESS_DEG, SUCCESS_REL, rotation_key, translation_key

MISSING = "–"
"""What a cell shows when the value does not exist (no ground truth, not recorded)."""

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2em auto; max-width: 1150px;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { margin-top: 1.8em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f2f2; } td.text, th.text { text-align: left; }
tbody tr:nth-child(even) { background: #fafafa; }
.meta td { text-align: left; border: none; padding: 0.1em 0.8em 0.1em 0; } .meta td:first-child { color: #666; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { color: #444; font-size: 0.92em; max-width: 60em; }
.missing { background: #fff6e0; border-left: 4px solid #e0a800; padding: 0.5em 0.8em; }
pre { background: #f6f6f6; padding: 0.8em; overflow-x: auto; font-size: 0.85em; }
.scroll { max-height: 40em; overflow-y: auto; display: inline-block; }
"""


@dataclass(frozen=True)
class Part:
    """One figure of the report: there (``missing`` is ``None``), or not, and why."""

    file: str
    """PNG path relative to the run folder, with forward slashes (it goes into ``src``)."""
    title: str
    caption: str
    missing: str | None = None


@dataclass(frozen=True)
class Page:
    """Everything the page shows."""

    title: str
    meta: list[tuple[str, str]]
    """(label, value) lines under the title: run folder, model, sequence, ..."""
    summary: RunSummary
    """``summarize(rows)``, with ``frames_total`` and ``complete`` where the run wrote them."""
    rows: list[FrameResult]
    parts: list[Part]
    settings: str
    """config.yml as written, or a sentence saying why it is not shown."""


def _e(value: object) -> str:
    return html.escape(str(value))


def _number(value: float | None, digits: int = 2) -> str:
    return MISSING if value is None else f"{value:.{digits}f}"


def _percent(rate: float, total: int) -> str:
    """A success rate with the counts behind it: 50% of 2 frames is not 50% of 200."""
    return f"{100 * rate:.0f}% ({round(rate * total)}/{total})"


def _table(header: Iterable[str], body: Iterable[Iterable[str]], text_columns: int = 1) -> str:
    """An HTML table whose first ``text_columns`` columns are text (left-aligned) and the rest numbers;
    the cells must already be escaped."""
    def cells(tag: str, values: Iterable[str]) -> str:
        text = ' class="text"'
        return "".join(f"<{tag}{text if i < text_columns else ''}>{v}</{tag}>" for i, v in enumerate(values))
    rows = "".join(f"<tr>{cells('td', row)}</tr>" for row in body)
    return f"<table><thead><tr>{cells('th', header)}</tr></thead><tbody>{rows}</tbody></table>"


def _frames_line(summary: RunSummary) -> str:
    done = summary.frames_done
    if summary.frames_total is None:
        return f"{done} (summary.json not written yet: the run is going on or was interrupted)"
    state = "complete" if summary.complete else "not finished: continue it with ns-invert --resume"
    return f"{done} of {summary.frames_total} ({state})"


def run_table(summary: RunSummary) -> str:
    truth = 0 if summary.frames_with_truth is None else summary.frames_with_truth
    lines = [("frames", _frames_line(summary)), ("frames with ground truth", str(truth))]
    if summary.wall_time_s is not None:
        lines += [("time per frame (s, mean)", _number(summary.mean_time_per_frame_s, 1)),
                  ("time in all (s)", _number(summary.wall_time_s, 0)),
                  ("loss of the last frame", _number(summary.final_loss, 5))]
    lines += clock_lines(summary)
    return _table(("run", ""), ((_e(k), _e(v)) for k, v in lines), text_columns=2)


def clock_lines(summary: RunSummary) -> list[tuple[str, str]]:
    """The clock's figures: frames skipped, latency, the first lock (where the run recorded them)."""
    lines = []
    if summary.clock is not None:
        lines.append(("clock", summary.clock))
    if summary.frames_skipped is not None:
        lines.append(("frames skipped (poses interpolated)", f"{summary.frames_skipped} of {summary.frames_done}"))
    if summary.latency_s is not None:
        latency = summary.latency_s
        lines.append(("latency of the estimated frames (s: mean, median, max)",
                      f"{latency.mean:.2f}, {latency.median:.2f}, {latency.max:.2f}"))
    if summary.rotation_deg is not None and summary.frames_estimated is not None:
        lines.append((f"first estimate under {LOCK_DEG:g}° (run's clock)", MISSING if summary.time_to_first_lock_s
                      is None else f"{summary.time_to_first_lock_s:.1f} s, frame {summary.first_lock_frame}"))
    return lines


ERRORS = (("rotation error (deg)", "rotation_deg", 1, 2), ("translation error (m)", "translation_m", 1, 3),
          ("translation error (% of range)", "translation_rel", 100, 2),
          ("SPEC2021 score (rad + relative translation)", "score", 1, 4))
"""Rows of the error table: label, :class:`RunSummary` field, scale, decimals."""
STATISTICS = ("mean", "median", "max", "final")
"""Columns of the error table: fields of :class:`ErrorStatistics`."""


def errors_table(summary: RunSummary | Accuracy, over: str = "the frames with ground truth") -> str:
    body = [(_e(label), *(_number(getattr(getattr(summary, name), s) * scale, digits) for s in STATISTICS))
            for label, name, scale, digits in ERRORS]
    return _table((_e(f"error over {over}"), *STATISTICS), body)


def success_table(summary: RunSummary | Accuracy) -> str:
    total = summary.frames if isinstance(summary, Accuracy) else summary.frames_with_truth
    body = [(_e(f"rotation error under {t:g}°"), _percent(summary.success_rotation[rotation_key(t)], total))
            for t in SUCCESS_DEG]
    body += [(_e(f"translation error under {100 * t:g}% of range"),
              _percent(summary.success_translation[translation_key(t)], total)) for t in SUCCESS_REL]
    return _table(("success", "frames"), body)


def summary_tables(summary: RunSummary) -> str:
    if summary.rotation_deg is None:
        return run_table(summary) + ('<p class="missing">No ground truth for these frames: errors and success '
                                     "rates cannot be computed.</p>")
    tables = run_table(summary) + errors_table(summary, "every frame with ground truth, interpolated ones included"
                                               if summary.frames_skipped else "the frames with ground truth")
    tables += success_table(summary)
    if summary.estimated_only is not None:
        estimated = summary.estimated_only
        tables += errors_table(estimated, f"the {estimated.frames} estimated frames alone") + success_table(estimated)
    return tables


def frames_table(rows: list[FrameResult]) -> str:
    header = ("frame", "image", "rotation (deg)", "translation (m)", "translation (% of range)", "SPEC score",
              "loss", "candidates", "dropped", "time (s)", "latency (s)")
    body = [(str(r.frame), _e(r.name + (" (interpolated)" if r.interpolated else "")), _number(r.rotation_deg),
             _number(r.translation_m, 3), MISSING if r.translation_rel is None else _number(100 * r.translation_rel),
             _number(r.score, 4), _number(r.loss, 5), str(r.candidates), str(r.dropped),
             _number(r.wall_time_s, 1), _number(r.latency_s, 1)) for r in rows]
    return f'<div class="scroll">{_table(header, body, text_columns=2)}</div>'


def _figure(part: Part) -> str:
    if part.missing is not None:
        return f'<h3>{_e(part.title)}</h3><p class="missing">Not in this report: {_e(part.missing)}</p>'
    return (f'<figure><h3>{_e(part.title)}</h3><img src="{_e(part.file)}" alt="{_e(part.title)}">'
            f"<figcaption>{_e(part.caption)}</figcaption></figure>")


def render(page: Page) -> str:
    meta = "".join(f"<tr><td>{_e(k)}</td><td>{_e(v)}</td></tr>" for k, v in page.meta)
    frames = frames_table(page.rows) if page.rows else "<p>No frame has finished yet.</p>"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{_e(page.title)}</title>
<style>{CSS}</style></head><body>
<h1>{_e(page.title)}</h1>
<table class="meta">{meta}</table>
<h2>Summary</h2>
{summary_tables(page.summary)}
<h2>Figures</h2>
{"".join(_figure(p) for p in page.parts)}
<h2>Frames</h2>
{frames}
<h2>Settings (config.yml)</h2>
<pre>{_e(page.settings)}</pre>
</body></html>
"""

