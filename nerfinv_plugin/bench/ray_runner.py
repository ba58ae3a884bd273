"""A grid's cells as Ray tasks, on a local Ray started for the run or on an existing cluster.

Each pending cell becomes one task that asks for ``cpus`` CPUs (torch in it uses that many threads) and,
when the cluster has GPUs and the cell does not run on the CPU, a ``gpus`` share of one. The driver (this
process) keeps the grid's files: it writes each cell's run folder and the tables as the cell's task
returns, through the same :class:`~nerfinv_plugin.bench.grid.Bench` as the local runner, so a grid can be
started on one machine, stopped, and continued on a cluster, or the other way round.

Where the files are:

- by default nodes share no filesystem. The files a cell opens (the model's ``config.yml``, checkpoint and
  ``dataparser_transforms.json``, the sequence, a camera file or mask folder, the training transforms for
  training-view starts) are read here and put in Ray's object store once per model and sequence. A task
  recreates them under a temporary folder of its node, at their absolute paths below it, runs there, and
  returns the files of its run folder. A cell that had begun (``state.pt``) is sent with its folder and
  continues. Results exist on the driver only once a cell has ended: a cell stopped on Ray (Ctrl-C here,
  a node lost) runs again from the state the driver had.
- with ``shared_storage``, every node sees the grid's paths at the same place (NFS, a cluster filesystem)
  and runs in the directory the driver runs in. Tasks open the model and sequence there and write their
  run folders directly into ``--out``, as the local runner does, so a stopped cell resumes at its last step.

Faults: a task whose worker process dies is run again by Ray, up to ``retries`` times; a cell whose Python
code raises is not retried, it comes back as failed with its one-line error, as with the local runner
(the next invocation tries it again).
"""

import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from nerfinv_plugin.bench.grid import Bench, Cell, GridError, one_line, run_inversion
from nerfinv_plugin.inversion.session import new_run_folder
from nerfinv_plugin.inversion.settings import InvertConfig, write_config
from nerfinv_plugin.model.loading import find_checkpoint
from nerfinv_plugin.model.loading import read_config as read_trainer_config
from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.results.folder import CONFIG, STATE, SUMMARY, RunFolder

TASK_PREFIX = "nerfinv-cell:"
"""Ray names each cell's task (and its worker process, ``ray::nerfinv-cell:<cell>``) with this prefix."""

Files = dict[str, bytes]
"""File contents by path: absolute paths of the driver's machine, or paths inside a run folder."""


def _tree(folder: Path) -> list[Path]:
    return sorted(p for p in Path(folder).rglob("*") if p.is_file())


def sequence_files(spec: str) -> list[Path]:
    """The files that reading the sequence ``spec`` opens (its layouts are those of ``data/sequences.py``):
    a Blender scene folder; a SHIRT trajectory's domain folder with the root's ``camera.json`` and every
    trajectory's label file (the shirt-labels starts draw from the others); an image folder."""
    path = Path(spec)
    if not path.exists() and ":" in spec:
        return _tree(Path(spec.rsplit(":", 1)[0]))
    trajectory = path if (path / f"{path.name}.json").is_file() else path.parent
    if (trajectory / f"{trajectory.name}.json").is_file():
        root = trajectory.parent
        labels = [p for p in root.glob("*/*.json") if p.stem == p.parent.name]
        camera = [root / "camera.json"] if (root / "camera.json").is_file() else []
        return camera + sorted(labels) + _tree(path if path != trajectory else trajectory / "synthetic")
    return _tree(path)


def model_files(config_yml: Path) -> list[Path]:
    """What loading a model opens: ``config.yml``, ``dataparser_transforms.json`` and the latest checkpoint."""
    trainer = read_trainer_config(config_yml)
    return [Path(config_yml), Path(config_yml).parent / "dataparser_transforms.json",
            find_checkpoint(config_yml, trainer, None)]


def extra_files(config: InvertConfig) -> list[Path]:
    """Other files a cell may open: ``--camera``, ``--masks`` and, for training-view starts, the model's
    training transforms (config.yml's data path, relative to where the driver runs)."""
    files = [Path(config.camera)] if config.camera is not None else []
    if config.masks is not None:
        files += _tree(Path(config.masks))
    if config.starts.source == "training-views":
        datamanager = read_trainer_config(config.load_config).pipeline.datamanager
        data = Path(datamanager.data or datamanager.dataparser.data or ".")
        files += [p for p in (data / "transforms_train.json", data / "transforms.json") if p.is_file()]
    return files


def read_files(paths: list[Path]) -> Files:
    return {str(Path(p).absolute()): Path(p).read_bytes() for p in paths}


def _below(root: Path, path: Path | str) -> Path:
    """Where the driver's absolute ``path`` is recreated on a node: under ``root``."""
    absolute = Path(path).absolute()
    return root / absolute.relative_to(absolute.anchor)


def _moved(config: InvertConfig, root: Path) -> InvertConfig:
    """``config`` with its absolute paths moved under ``root`` (relative ones resolve from the recreated
    working directory)."""
    def move(path: Path | str | None) -> Any:
        if path is None or not Path(path).is_absolute():
            return path
        return type(path)(_below(root, path))
    return replace(config, load_config=move(config.load_config), sequence=move(config.sequence),
                   camera=move(config.camera), masks=move(config.masks), output_dir=root / "out")


@dataclass
class SentCell:
    """What a task is sent besides the input files."""

    config: InvertConfig
    """The cell's settings as the grid gives them (paths as the driver sees them)."""
    run_dir: str
    """The cell's run folder on the driver."""
    cwd: str
    """The driver's working directory, where relative paths start."""
    folder: Files = field(default_factory=dict)
    """The run folder's files on the driver (a cell that had begun), but its config.yml."""


@dataclass
class CellOutcome:
    """What a task returns: the run folder's files, or the one-line error of a cell that raised."""

    files: Files
    error: str | None = None


def _use_granted_cpus() -> None:
    """torch's threads as the CPUs Ray granted the task (it would otherwise take the node's)."""
    import ray

    torch.set_num_threads(max(1, int(ray.get_runtime_context().get_assigned_resources().get("CPU", 1))))


def run_sent_cell(cell: SentCell, *inputs: Files) -> CellOutcome:
    """A Ray task: run a cell from the files it was sent, in a temporary folder of this node."""
    _use_granted_cpus()
    before = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="nerfinv-cell-") as tmp:
        root = Path(tmp)
        for files in inputs:
            for path, data in files.items():
                _below(root, path).parent.mkdir(parents=True, exist_ok=True)
                _below(root, path).write_bytes(data)
        config = _moved(cell.config, root)
        run_dir = new_run_folder(config)
        run_dir.mkdir(parents=True)
        for name, data in cell.folder.items():
            (run_dir / name).parent.mkdir(parents=True, exist_ok=True)
            (run_dir / name).write_bytes(data)
        cwd = _below(root, cell.cwd)
        cwd.mkdir(parents=True, exist_ok=True)
        os.chdir(cwd)
        try:
            run_inversion(config, run_dir)
        except Exception as err:
            return CellOutcome({}, one_line(err).replace(str(root), ""))  # the paths as the driver knows them
        finally:
            os.chdir(before)
        folder = RunFolder(run_dir)
        summary = folder.summary()
        if summary is not None:  # where the driver keeps the run, not where it ran
            folder.write_summary(replace(summary, run=cell.run_dir, model=str(cell.config.load_config),
                                         sequence=str(cell.config.sequence)))
        return CellOutcome({str(p.relative_to(run_dir)): p.read_bytes() for p in _tree(run_dir) if p.name != CONFIG})


def run_shared_cell(config: InvertConfig, run_dir: str, cwd: str) -> CellOutcome:
    """A Ray task: run a cell on storage every node shares, from the driver's working directory."""
    _use_granted_cpus()
    before = os.getcwd()
    try:
        os.chdir(cwd)  # a node without the driver's directory fails the cell with that message
        run_inversion(config, Path(run_dir))
    except Exception as err:
        return CellOutcome({}, one_line(err))
    finally:
        os.chdir(before)
    return CellOutcome({})


def receive(run_dir: Path, config: InvertConfig, files: Files) -> None:
    """Write a cell's returned run folder on the driver: its settings first and ``summary.json`` (the mark
    of a finished cell) last, each file atomically."""
    run_dir.mkdir(parents=True, exist_ok=True)
    write_config(run_dir / CONFIG, replace(config, resume=None))
    for name in sorted(files, key=lambda n: (n == SUMMARY, n != STATE, n)):
        (run_dir / name).parent.mkdir(parents=True, exist_ok=True)
        write_atomic(run_dir / name, files[name])


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise GridError("--ray needs Ray, which is not installed: pip install 'nerfinv[ray]'") from None
    return ray


@dataclass
class RayRunner:
    """Runs a bench's cells as Ray tasks (a :data:`~nerfinv_plugin.bench.grid.CellRunner`)."""

    address: str | None = None
    """``ray.init``'s address of an existing cluster (``auto``, ``HOST:PORT``, ``ray://HOST:10001``); ``None``
    starts a local Ray for the run (or uses the one this process already started)."""
    cpus: int = 1
    """CPUs each cell asks for; torch in the cell uses as many threads."""
    gpus: float = 0.25
    """Share of a GPU each cell asks for when the cluster has GPUs and the cell's device is not cpu."""
    retries: int = 3
    """Times Ray runs a cell again whose worker process died."""
    shared_storage: bool = False
    """Every node sees the grid's paths at the same place: cells read and write them there."""

    def __post_init__(self) -> None:
        if self.cpus < 1 or self.gpus < 0 or self.retries < 0:
            raise GridError(f"--ray-cpus must be >= 1, --ray-gpus and --ray-retries >= 0 (got {self.cpus}, "
                            f"{self.gpus:g}, {self.retries})")

    def __call__(self, bench: Bench, cells: list[Cell]) -> Iterator[tuple[Cell, dict]]:
        ray = _ray()
        started = not ray.is_initialized()
        if started:
            # Ray gives a new node 30 s to register; a busy machine (a shared 2-core one) can need more.
            os.environ.setdefault("RAY_raylet_start_wait_time_s", "180")
            # Ray runs its workers at nice 15; the cells are this run's work, so they run at the priority the
            # local runner's would (under nice 15 they got 2% of a core beside other work, docs/bench.md).
            os.environ.setdefault("RAY_worker_niceness", "0")
            try:
                ray.init(address=self.address, include_dashboard=False, log_to_driver=False)
            except (ConnectionError, ValueError, RuntimeError) as err:
                where = f"the Ray cluster at {self.address}" if self.address else "a local Ray"
                raise GridError(f"cannot start or reach {where}: {one_line(err)} (start one with "
                                "'ray start --head', or check --ray's address)") from None
        running: dict[Any, Cell] = {}
        try:
            resources = ray.cluster_resources()
            bench.events.info(f"Ray: {resources.get('CPU', 0):g} CPUs, {resources.get('GPU', 0):g} GPUs; "
                              f"{self.cpus} CPU(s) per cell, "
                              f"{'shared storage' if self.shared_storage else 'files sent through the object store'}")
            task = ray.remote(run_shared_cell if self.shared_storage else run_sent_cell)
            sent: dict[tuple[str, ...], Any] = {}
            for cell in cells:
                try:
                    running[self._submit(ray, task, bench, cell, resources.get("GPU", 0) > 0, sent)] = cell
                except Exception as err:  # a cell whose files cannot be read or whose folder is refused
                    yield cell, bench.failed(cell, one_line(err))
            while running:
                [ref], _ = ray.wait(list(running), num_returns=1)
                cell = running.pop(ref)
                yield cell, self._ended(ray, bench, cell, ref)
        finally:
            for ref in running:  # Ctrl-C: stop what still runs, keep what ended
                ray.cancel(ref, force=True)
            if started:
                ray.shutdown()

    def _submit(self, ray: Any, task: Any, bench: Bench, cell: Cell, has_gpus: bool,
                sent: dict[tuple[str, ...], Any]) -> Any:
        """Submit a cell's task; ``sent`` holds the object-store references of the inputs already put."""
        bench.check_settings(cell)
        config, run_dir = bench.configs[cell.label], bench.run_dir(cell)
        options = {"name": f"{TASK_PREFIX}{cell.label}", "num_cpus": self.cpus, "max_retries": self.retries,
                   "retry_exceptions": False,
                   "num_gpus": self.gpus if has_gpus and config.device != "cpu" else 0}
        if self.shared_storage:
            return task.options(**options).remote(config, str(run_dir.absolute()), os.getcwd())
        inputs = []
        for paths in (model_files(config.load_config), sequence_files(str(config.sequence)), extra_files(config)):
            key = tuple(str(Path(p).absolute()) for p in paths)
            if key not in sent:  # once per model and sequence, however many cells use them
                sent[key] = ray.put(read_files(paths))
            inputs.append(sent[key])
        folder = {str(p.relative_to(run_dir)): p.read_bytes() for p in _tree(run_dir) if p.name != CONFIG} \
            if run_dir.is_dir() else {}
        job = SentCell(config, str(run_dir), os.getcwd(), folder)
        return task.options(**options).remote(job, *inputs)

    def _ended(self, ray: Any, bench: Bench, cell: Cell, ref: Any) -> dict:
        try:
            outcome = ray.get(ref)
        except ray.exceptions.RayError as err:  # its worker died more than `retries` times
            return bench.failed(cell, one_line(err))
        if outcome.error is not None:
            return bench.failed(cell, outcome.error)
        if not self.shared_storage:
            receive(bench.run_dir(cell), bench.configs[cell.label], outcome.files)
        return bench.finished(cell)
