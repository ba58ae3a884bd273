"""A grid of inversions: every case (a model and a sequence) under every variant (a few settings changed)
with every seed, each cell one ``ns-invert`` run in ``<out>/<grid>/nerfinv/<case>-<variant>-s<seed>/``.

A grid runs for hours, so it is built to be stopped and started again:

- a cell whose run finished (``summary.json``) is read back, not run again;
- a cell stopped half way continues (``Inversion.resume``) and ends with the numbers an uninterrupted run
  would have given;
- a cell that raises is recorded as failed with its one-line error and the grid goes on; the next
  invocation tries it again;
- a cell folder written with other settings than the grid's now are is refused rather than resumed or
  counted, so that editing a variant never mixes old and new results in one table;
- the tables are rewritten after every cell.

Cells run seed by seed (all cases and variants of seed 0, then of seed 1, ...), so a grid stopped early
still compares every variant on the same runs.
"""

import dataclasses
import re
from collections.abc import Callable, Iterable, Iterator
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from nerfinv_plugin.bench.plots import write_plots
from nerfinv_plugin.bench.scoring import cell_metrics
from nerfinv_plugin.bench.tables import write_tables
from nerfinv_plugin.inversion.session import Events, Inversion, new_run_folder
from nerfinv_plugin.inversion.settings import InvertConfig, defaults_with_preset, read_config, to_dict, updated
from nerfinv_plugin.results.folder import CONFIG, SUMMARY, RunFolder

GRID_KEYS = ("name", "preset", "overrides", "seeds", "cases", "variants")
CASE_KEYS = ("load_config", "sequence", "overrides")
RESERVED = ("load_config", "sequence", "output_dir", "name", "timestamp", "resume", "seed", "preset")
"""Settings the grid sets for every cell itself: overriding them would break the folder layout or the
seeds' meaning."""
LABEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")
"""Labels name folders: no slashes, spaces or leading dots."""


class GridError(Exception):
    """A grid file or a cell that cannot be used; the message says which and why."""


@dataclass
class Case:
    """A model and a sequence, with the settings that belong to them (target centre, resolution, frames)."""

    label: str
    load_config: Path
    sequence: str
    overrides: dict = field(default_factory=dict)


@dataclass
class Variant:
    """What is compared: a few settings changed from the grid's base."""

    label: str
    overrides: dict = field(default_factory=dict)


@dataclass
class Grid:
    """Every case under every variant with every seed."""

    name: str
    cases: list[Case]
    variants: list[Variant]
    seeds: list[int]
    preset: str | None = None
    """Base settings: a preset of ``configs/`` by name, or a YAML file (relative to the current directory)."""
    overrides: dict = field(default_factory=dict)
    """Base settings on top of the preset, for every cell."""

    def definition(self) -> dict:
        """The grid in the grid-file format (written into grid.json, so a table says what produced it)."""
        return {"name": self.name, "preset": self.preset, "overrides": self.overrides, "seeds": self.seeds,
                "cases": {c.label: {"load_config": str(c.load_config), "sequence": c.sequence,
                                    "overrides": c.overrides} for c in self.cases},
                "variants": {v.label: v.overrides for v in self.variants}}


@dataclass
class Cell:
    """One run of the grid."""

    case: Case
    variant: Variant
    seed: int

    @property
    def label(self) -> str:
        """The run folder's name."""
        return f"{self.case.label}-{self.variant.label}-s{self.seed}"


def merge(base: dict, changes: dict) -> dict:
    """``changes`` on top of ``base``, group by group (a variant's ``starts.count`` keeps the base's
    ``starts.source``)."""
    merged = dict(base)
    for key, value in changes.items():
        both = isinstance(merged.get(key), dict) and isinstance(value, dict)
        merged[key] = merge(merged[key], value) if both else value
    return merged


def _nested(overrides: Any, where: str) -> dict:
    if not isinstance(overrides, dict):
        raise GridError(f"{where}: expected a mapping of settings, such as 'monte_carlo.reset_lr: false', "
                        f"not {overrides!r}")
    nested: dict = {}
    for key, value in overrides.items():
        *groups, leaf = str(key).replace("-", "_").split(".")
        tree = {leaf: _nested(value, where) if isinstance(value, dict) else value}
        for group in reversed(groups):
            tree = {group: tree}
        nested = merge(nested, tree)
    return nested


def expand(overrides: Any, where: str) -> dict:
    """Dotted keys (``monte_carlo.reset_lr: false``) as the nested mappings of ``config.yml``, which both
    spellings (and any mix of them) end up as; dashes read as underscores, as on the command line."""
    nested = _nested(overrides, where)
    reserved = sorted(set(nested) & set(RESERVED))
    if reserved:
        raise GridError(f"{where}: {', '.join(reserved)} cannot be overridden (the grid sets them for every cell: "
                        "cases give the model and sequence, 'seeds' the seeds, 'preset' the preset)")
    return nested


def parse_overrides(items: Iterable[str], where: str) -> dict:
    """``KEY=VALUE`` strings from a command line; values read as YAML (``false``, ``[3, 1]``, ``cuda``)."""
    pairs = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise GridError(f"{where}: '{item}' is not KEY=VALUE (such as monte_carlo.reset_lr=false)")
        pairs[key] = yaml.safe_load(value)
    return expand(pairs, where)


def _label(value: Any, where: str) -> str:
    if not isinstance(value, (str, int)) or not LABEL.fullmatch(str(value)):
        raise GridError(f"{where}: label {value!r} must be letters, digits, '.', '_', '+' or '-' (it names folders)")
    return str(value)


def _mapping(value: Any, where: str, keys: tuple[str, ...] | None = None) -> dict:
    if not isinstance(value, dict) or not value:
        raise GridError(f"{where}: expected a non-empty mapping")
    unknown = sorted(map(str, set(value) - set(keys))) if keys else []
    if unknown:
        raise GridError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(keys or ())}")
    return value


def _case(label: Any, spec: Any, where: str) -> Case:
    where = f"{where}: case {label}"
    spec = _mapping(spec, where, CASE_KEYS)
    missing = [k for k in ("load_config", "sequence") if not spec.get(k)]
    if missing:
        raise GridError(f"{where}: needs {' and '.join(missing)}")
    return Case(_label(label, where), Path(spec["load_config"]), str(spec["sequence"]),
                expand(spec.get("overrides") or {}, where))


def _seeds(value: Any, where: str) -> list[int]:
    seeds = value if isinstance(value, list) else [value]
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds) \
            or len(set(seeds)) != len(seeds):
        raise GridError(f"{where}: seeds must be distinct integers, not {value!r}")
    return seeds


def grid_from_dict(data: Any, where: str, default_name: str) -> Grid:
    data = _mapping(data, where, GRID_KEYS)
    cases = _mapping(data.get("cases"), f"{where}: cases")
    variants = _mapping(data.get("variants") or {"base": {}}, f"{where}: variants")
    return Grid(name=_label(data.get("name", default_name), f"{where}: name"),
                cases=[_case(label, spec, where) for label, spec in cases.items()],
                variants=[Variant(_label(label, f"{where}: variant"), expand(spec or {}, f"{where}: variant {label}"))
                          for label, spec in variants.items()],
                seeds=_seeds(data.get("seeds", [0]), f"{where}: seeds"), preset=data.get("preset"),
                overrides=expand(data.get("overrides") or {}, f"{where}: overrides"))


def read_grid(path: Path) -> Grid:
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise GridError(f"cannot read grid file {path}: {err}".splitlines()[0]) from err
    return grid_from_dict(data, str(path), Path(path).stem)


def with_cases(grid: Grid, specs: Iterable[tuple[str, str, str]]) -> Grid:
    """Only the cases given as (label, config.yml, sequence); a label of the grid file keeps that case's
    overrides (its target centre, resolution, frames), so only the paths change."""
    known = {c.label: c.overrides for c in grid.cases}
    cases = [Case(_label(label, "--case"), Path(config), sequence, known.get(label, {}))
             for label, config, sequence in specs]
    return dataclasses.replace(grid, cases=cases)


def base_config(grid: Grid) -> InvertConfig:
    return defaults_with_preset(["--preset", grid.preset]) if grid.preset else InvertConfig()


def cell_config(grid: Grid, cell: Cell, out: Path) -> InvertConfig:
    """Base (preset, then the grid's overrides), then the case's, then the variant's; then what the grid
    owns: paths, folder and seed."""
    config = base_config(grid)
    for where, overrides in ((f"grid {grid.name}: overrides", grid.overrides),
                             (f"grid {grid.name}: case {cell.case.label}", cell.case.overrides),
                             (f"grid {grid.name}: variant {cell.variant.label}", cell.variant.overrides)):
        config = updated(config, overrides, where)
    return dataclasses.replace(config, load_config=cell.case.load_config, sequence=cell.case.sequence,
                               output_dir=Path(out), name=grid.name, timestamp=cell.label, seed=cell.seed)


def one_line(err: BaseException) -> str:
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__


def _flat(data: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in data.items():
        flat |= _flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value}
    return flat


@dataclass
class GridEvents:
    """What a front end hears while a grid runs. All optional."""

    begin: Callable[[list[dict]], None] = lambda records: None
    """The cells' state before this invocation runs any (finished ones are ``done``)."""
    cell_start: Callable[[Cell, bool], None] = lambda cell, resumed: None
    """A cell's inversion starts in this process; ``resumed`` when it continues an interrupted one."""
    cell_end: Callable[[dict], None] = lambda record: None
    """A cell ran (done or failed); its record is already in the tables."""
    inversion: Callable[[Cell], Events] = lambda cell: Events()
    """The events of a cell's inversion in this process (its steps and frames)."""
    info: Callable[[str], None] = lambda message: None
    """Where the cells run, when not in this process."""


def run_inversion(config: InvertConfig, path: Path, events: Events | None = None) -> None:
    """A cell's work, wherever it runs: the inversion of ``config`` in the run folder ``path``, started
    afresh or continued from the step its ``state.pt`` holds."""
    Inversion(config, RunFolder(path), events or Events()).run()


CellRunner = Callable[["Bench", list[Cell]], Iterator[tuple[Cell, dict]]]
"""Runs the given pending cells of a bench and yields each cell with its record (from
:meth:`Bench.finished` or :meth:`Bench.failed`) as soon as it ended, in any order. The local runner is
:func:`in_process`; ``nerfinv_plugin.bench.ray_runner.RayRunner`` runs cells as Ray tasks."""


def in_process(bench: "Bench", cells: list[Cell]) -> Iterator[tuple[Cell, dict]]:
    """One cell after the other in this process."""
    for cell in cells:
        yield cell, bench.run_here(cell)


class Bench:
    """Runs a grid into ``<out>/<grid name>/``; the runner chooses where the cells run, the tables are
    written here."""

    def __init__(self, grid: Grid, out: Path, events: GridEvents | None = None, runner: CellRunner = in_process):
        self.grid, self.events, self.runner = grid, events or GridEvents(), runner
        self.folder = Path(out) / grid.name
        self.cells = [Cell(case, variant, seed) for seed in grid.seeds for case in grid.cases
                      for variant in grid.variants]
        labels = [cell.label for cell in self.cells]
        shared = sorted({label for label in labels if labels.count(label) > 1})
        if shared:
            raise GridError(f"grid {grid.name}: cells would share the folder(s) {', '.join(shared)} (a case label "
                            "ending as another begins); rename a case or variant")
        # Every cell's settings are built now, so a typo in the last variant fails before hours of runs.
        self.configs = {cell.label: cell_config(grid, cell, Path(out)) for cell in self.cells}

    def run_dir(self, cell: Cell) -> Path:
        return new_run_folder(self.configs[cell.label])

    def run(self) -> list[dict]:
        """Run every cell not finished yet; return one record per cell, in grid order. The tables are
        rewritten as each cell ends, so an interruption keeps every cell that ended."""
        records = {cell.label: self._snapshot(cell) for cell in self.cells}
        self._write(records)
        self.events.begin(list(records.values()))
        pending = [cell for cell in self.cells if records[cell.label]["status"] == "pending"]
        try:
            with closing(self.runner(self, pending)) as ended:  # closed at once on Ctrl-C: it stops what runs
                for cell, record in ended:
                    records[cell.label] = record
                    self._write(records)
                    self.events.cell_end(record)
        finally:
            pixels = {v.label: v.overrides["pixels"] for v in self.grid.variants if "pixels" in v.overrides}
            write_plots(self.folder, self.grid.name, list(records.values()), pixels)
        return list(records.values())

    def _write(self, records: dict[str, dict]) -> None:
        write_tables(self.folder, self.grid.definition(), list(records.values()))

    def _record(self, cell: Cell, status: str, **values: Any) -> dict:
        return {"cell": cell.label, "case": cell.case.label, "variant": cell.variant.label, "seed": cell.seed,
                "status": status, "run": str(self.run_dir(cell)), **values}

    def failed(self, cell: Cell, error: str) -> dict:
        """The record of a cell that raised ``error`` (one line)."""
        return self._record(cell, "failed", error=error)

    def finished(self, cell: Cell) -> dict:
        """The record of a cell whose run folder is complete, scored from its results; failed when they
        cannot be scored (no ground truth)."""
        try:
            return self._record(cell, "done", **cell_metrics(RunFolder(self.run_dir(cell)).rows()))
        except Exception as err:
            return self.failed(cell, one_line(err))

    def _snapshot(self, cell: Cell) -> dict:
        """What the cell's folder holds before this invocation runs anything."""
        if not (self.run_dir(cell) / SUMMARY).is_file():
            return self._record(cell, "pending")
        try:
            self.check_settings(cell)
        except GridError as err:
            return self.failed(cell, one_line(err))
        return self.finished(cell)

    def run_here(self, cell: Cell) -> dict:
        """Run (or continue) a cell in this process and return its record."""
        path = self.run_dir(cell)
        try:
            self.check_settings(cell)
            self.events.cell_start(cell, (path / CONFIG).is_file())
            run_inversion(self.configs[cell.label], path, self.events.inversion(cell))
        except Exception as err:
            return self.failed(cell, one_line(err))
        return self.finished(cell)

    def check_settings(self, cell: Cell) -> None:
        """Refuse a folder started with other settings than the cell's now (an edited grid file)."""
        saved = self.run_dir(cell) / CONFIG
        if not saved.is_file():
            return
        old, new = _flat(to_dict(read_config(saved))), _flat(to_dict(self.configs[cell.label]))
        changed = [f"{key} {old.get(key)!r} -> {value!r}" for key, value in new.items() if old.get(key) != value]
        if changed:
            raise GridError(f"{saved.parent} was started with other settings ({'; '.join(changed)}): delete that "
                            "folder to run the cell again, or give another --out")
