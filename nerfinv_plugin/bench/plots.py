"""The grid's figures, beside its table: success rates per variant (thesis' k/n counts as bars), the
spread of final errors per variant (a median hides a bimodal outcome: converged or lost), and, for
pixel-count variants, what each count costs against what it buys (thesis fig. 5.4).

Built on matplotlib's object API with an Agg canvas, as the run reports are: no global pyplot state, no
display needed.
"""

import io
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from nerfinv_plugin.bench.scoring import FIRST_UNDER_DEG, SUCCESS_DEG, aggregate, under_key
from nerfinv_plugin.results.atomic import write_atomic

DPI = 120
SUCCESS_PNG = "success.png"
FINAL_ERROR_PNG = "final_error.png"
PIXELS_PNG = "pixels.png"


def _save(figure: Figure, path: Path) -> None:
    """Written aside and renamed, as the tables are: a viewer never opens half a PNG."""
    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI, bbox_inches="tight")
    write_atomic(path, buffer.getvalue())


def _legend_outside(ax: Axes) -> None:
    """Beside the axes: bars near 100% and points anywhere leave no free corner inside."""
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)


def success_figure(name: str, records: list[dict]) -> Figure:
    groups = [g for g in aggregate(records, by_case=False) if g["done"]]
    figure = Figure(figsize=(max(6.0, 1.2 * len(SUCCESS_DEG) * max(1, len(groups)) / 2), 4.2))
    ax = figure.add_subplot()
    x, width = np.arange(len(SUCCESS_DEG)), 0.8 / len(groups)
    for i, group in enumerate(groups):
        counts = [group["successes"][under_key(t)] for t in SUCCESS_DEG]
        bars = ax.bar(x + (i - (len(groups) - 1) / 2) * width, [100 * k / group["done"] for k in counts], width,
                      label=f"{group['variant']} (n={group['done']})")
        ax.bar_label(bars, labels=[f"{k}/{group['done']}" for k in counts], fontsize=7, padding=1)
    ax.set_xticks(x, [f"< {t:g} deg" for t in SUCCESS_DEG])
    ax.set_ylim(0, 112)
    ax.set_xlabel("threshold on the rotation error of the last frame")
    ax.set_ylabel("runs under the threshold (%)")
    ax.set_title(f"{name}: success rate per variant, all cases")
    _legend_outside(ax)
    ax.grid(axis="y", alpha=0.3)
    return figure


def error_figure(name: str, records: list[dict]) -> Figure:
    done = [r for r in records if r["status"] == "done"]
    variants = list(dict.fromkeys(r["variant"] for r in done))
    cases = list(dict.fromkeys(r["case"] for r in done))
    figure = Figure(figsize=(max(6.0, 1.1 * len(variants) + 2), 4.5))
    ax = figure.add_subplot()
    errors = [[max(r["final_rotation_deg"], 1e-3) for r in done if r["variant"] == v] for v in variants]
    ax.boxplot(errors, positions=range(len(variants)), widths=0.5, showfliers=False)
    jitter = np.random.default_rng(0)  # fixed, so that the figure of the same table is the same image
    for colour, case in enumerate(cases):
        runs = [r for r in done if r["case"] == case]
        positions = [variants.index(r["variant"]) for r in runs]
        ax.scatter(np.array(positions) + jitter.uniform(-0.15, 0.15, len(runs)),
                   [max(r["final_rotation_deg"], 1e-3) for r in runs], s=16, alpha=0.8, color=f"C{colour % 10}",
                   label=case, zorder=3)
    ax.axhline(FIRST_UNDER_DEG, color="grey", linestyle="--", linewidth=1, label=f"{FIRST_UNDER_DEG:g} deg")
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.set_xticks(range(len(variants)), variants, rotation=20 if len(variants) > 4 else 0)
    ax.set_xlabel("variant")
    ax.set_ylabel("rotation error of the last frame (deg, log scale)")
    ax.set_title(f"{name}: final error per variant (box: quartiles; points: runs, by case)")
    _legend_outside(ax)
    ax.grid(axis="y", alpha=0.3, which="both")
    return figure


def pixels_figure(name: str, records: list[dict], pixels: dict[str, int]) -> Figure:
    """One line per case through its pixel-count variants: time per frame against median final error."""
    groups = [g for g in aggregate(records, by_case=True) if g["variant"] in pixels and g["done"]]
    figure = Figure(figsize=(6.5, 4.5))
    ax = figure.add_subplot()
    for colour, case in enumerate(dict.fromkeys(g["case"] for g in groups)):
        points = sorted((pixels[g["variant"]], g["mean_time_per_frame_s"], g["median_final_rotation_deg"])
                        for g in groups if g["case"] == case)
        ax.plot([p[1] for p in points], [p[2] for p in points], marker="o", color=f"C{colour % 10}", label=case)
        for count, time_s, error in points:
            ax.annotate(f"{count} px", (time_s, error), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_ylim(bottom=0)
    ax.set_xlim(left=0)
    ax.set_xlabel("mean time per frame (s)")
    ax.set_ylabel("median rotation error of the last frame (deg)")
    ax.set_title(f"{name}: pixels per iteration, cost against error")
    _legend_outside(ax)
    ax.grid(alpha=0.3)
    return figure


def write_plots(folder: Path, name: str, records: list[dict], pixels: dict[str, int]) -> list[Path]:
    """The figures that the finished cells allow; ``pixels`` maps pixel-count variants to their count."""
    done = [r for r in records if r["status"] == "done"]
    if not done:
        return []
    figures = {SUCCESS_PNG: success_figure(name, records), FINAL_ERROR_PNG: error_figure(name, records)}
    if len({r["variant"] for r in done if r["variant"] in pixels}) > 1:
        figures[PIXELS_PNG] = pixels_figure(name, records, pixels)
    for file, figure in figures.items():
        _save(figure, folder / file)
    return [folder / file for file in figures]
