"""``ns-invert-bench``: run an experiment grid (cases x variants x seeds) of ``ns-invert`` runs and tabulate
how often each variant ends on the target, as the thesis' chapter 5 counts it."""

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from tyro.conf import UseAppendAction, arg

from nerfinv_plugin.bench.grid import (
    Bench,
    Cell,
    Grid,
    GridError,
    GridEvents,
    merge,
    parse_overrides,
    read_grid,
    with_cases,
)
from nerfinv_plugin.bench.scoring import SUCCESS_DEG, aggregate, under_key
from nerfinv_plugin.bench.tables import TABLE_MD
from nerfinv_plugin.cli import Interrupted, run
from nerfinv_plugin.inversion.session import Events
from nerfinv_plugin.inversion.settings import SettingsError


@dataclass
class BenchCommand:
    """Run every case of a grid file under every variant and seed (one ns-invert run each), skipping the
    runs already finished and continuing interrupted ones, and write grid.csv, table.md, grid.json and
    figures into <out>/<grid name>/. Run the same command again to continue a stopped grid. See
    docs/bench.md and the grids in configs/bench/."""

    grid: Path
    """Grid file (YAML): base preset and overrides, cases (model config.yml and sequence), variants and
    seeds. Paths in it are relative to the current directory."""
    out: Path = Path("outputs")
    """Results root: the grid writes <out>/<grid name>/ (its runs in nerfinv/<case>-<variant>-s<seed>/)."""
    case: Annotated[tuple[tuple[str, str, str], ...], UseAppendAction, arg(metavar="LABEL CONFIG_YML SEQUENCE")] = ()
    """Run these cases instead of the grid file's: LABEL CONFIG_YML SEQUENCE, repeated. A LABEL of the
    grid file keeps that case's overrides (target, resolution, frames); only its paths change."""
    seeds: tuple[int, ...] | None = None
    """Seeds to run instead of the grid file's (the thesis ran each case 10 times: 0 1 2 3 4 5 6 7 8 9)."""
    preset: str | None = None
    """Base preset instead of the grid file's (a name in configs/ or a YAML file)."""
    override: tuple[str, ...] = ()
    """Base settings KEY=VALUE on top of the grid file's, for every cell, with dotted keys and YAML values:
    device=cuda stop=5 monte_carlo.keep=[5,5]."""

    def load(self) -> Grid:
        """The grid file with this command line's replacements."""
        grid = read_grid(self.grid)
        if self.case:
            grid = with_cases(grid, self.case)
        changes = {"overrides": merge(grid.overrides, parse_overrides(self.override, "--override"))}
        if self.seeds is not None:
            changes["seeds"] = list(self.seeds)
        if self.preset is not None:
            changes["preset"] = self.preset
        return dataclasses.replace(grid, **changes)

    def main(self) -> None:
        bench_grid(self.load(), self.out, Console(soft_wrap=True))  # a cell's error on one line


def _cell_line(record: dict) -> str:
    if record["status"] == "failed":
        return f"[red]{record['cell']}: failed: {escape(record['error'])}[/red]"
    return (f"{record['cell']}: final rotation error {record['final_rotation_deg']:.2f} deg, translation "
            f"{record['final_translation_m']:.3f} m, {record['frames']} frames in {record['wall_time_s']:.0f} s")


def _variant_line(group: dict) -> str:
    counts = ", ".join(f"{group['successes'][under_key(t)]}/{group['done']} < {t:g} deg" for t in SUCCESS_DEG)
    pending = group["cells"] - group["done"] - group["failed"]
    return f"{group['variant']}: {counts} ({group['failed']} failed, {pending} to run)"


def bench_grid(grid: Grid, out: Path, console: Console) -> list[dict]:
    """Run with a progress display: cells done of all, and the steps of the cell running."""
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        cells = progress.add_task("cells done", total=None)
        steps = progress.add_task("", total=None, visible=False)

        def begin(records: list[dict]) -> None:
            progress.update(cells, total=len(records), completed=sum(r["status"] == "done" for r in records))

        def cell_start(cell: Cell, resumed: bool) -> None:
            progress.update(steps, description=f"{cell.label} ({'resumed' if resumed else 'new'}): steps",
                            completed=0, total=None, visible=True)

        def cell_end(record: dict) -> None:
            console.print(_cell_line(record))
            progress.update(steps, visible=False)
            progress.advance(cells)

        def inversion(cell: Cell) -> Events:
            return Events(begin=lambda total, done, iterations: progress.update(steps, total=total, completed=done),
                          step=lambda row: progress.advance(steps),
                          warn=lambda message: console.print(f"[yellow]{cell.label}: {escape(message)}[/yellow]"))

        bench = Bench(grid, out, GridEvents(begin, cell_start, cell_end, inversion))
        console.print(f"grid {grid.name}: {len(bench.cells)} cells into {bench.folder}")
        try:
            records = bench.run()
        except KeyboardInterrupt:
            raise Interrupted(f"interrupted; the finished cells are in {bench.folder / TABLE_MD}. Run the same "
                              "command again to continue (the cell that was running resumes where it stopped)") \
                from None
    for group in aggregate(records, by_case=False):
        console.print(f"[bold]{_variant_line(group)}[/bold]")
    console.print(f"table: {bench.folder / TABLE_MD}")
    return records


def entrypoint() -> None:
    run(BenchCommand, "ns-invert-bench", GridError, SettingsError)


if __name__ == "__main__":
    entrypoint()
