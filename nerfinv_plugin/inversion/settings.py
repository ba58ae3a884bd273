"""Everything an ``ns-invert`` run is configured by, as dataclasses (tyro builds the command line from them,
with each field's docstring as its help), and their round trip through YAML: the ``config.yml`` written
into every run folder, and the presets in ``configs/`` (partial YAML files of the same shape)."""

import dataclasses
import sys
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

import yaml

from nerfinv_plugin.initialization.bank import BankConfig
from nerfinv_plugin.inversion.clock import ClockMode
from nerfinv_plugin.inversion.optimizer import OptimizerConfig
from nerfinv_plugin.inversion.sampling import Strategy
from nerfinv_plugin.inversion.tracker import MonteCarloConfig, Region
from nerfinv_plugin.inversion.validation import SettingsError, validate
from nerfinv_plugin.model.loading import Device


@dataclass
class StartConfig:
    """Where the candidates of the first Monte Carlo step come from (dataset frame, metres)."""

    source: Literal["bank", "training-views", "sphere-shell", "volume", "prior", "truth-offset",
                    "shirt-labels"] = "bank"
    """bank: hypotheses from matching the first frame against views rendered from the model (needs nothing
    but the model and the image: the mission's case); training-views: poses of the model's training images
    (the thesis' default; needs the training data where config.yml says it is); sphere-shell: cameras at
    --starts.range-m looking at the target, random roll (without --starts.range-m it takes the first frame's
    true range: an evaluation protocol); volume: cameras anywhere between min-range-m and max-range-m (the
    thesis' SPEED+ sampling); prior: around an approximate first pose given as a SHIRT label (prior-q,
    prior-r), turned up to 'max-deg' per Euler angle and shifted up to 'shift-m' per axis; truth-offset:
    turned 'min-deg' to 'max-deg' away from the first frame's true pose and shifted by 'shift-m' (iNeRF's
    evaluation protocol: reads the ground truth); shirt-labels: poses drawn from the labels of the SHIRT
    trajectories in the sequence's root, leaving out the frames this run estimates (the thesis' SHIRT
    protocol: reads ground truth)."""
    count: int = 15
    """Number of starting candidates (bank: the best hypotheses, kept apart on SO(3))."""
    range_m: float | None = None
    """sphere-shell radius. Unset: the true range of the first frame (reads the ground truth)."""
    min_range_m: float = 2.0
    """volume: nearest camera distance from the target."""
    max_range_m: float = 9.0
    """volume: farthest camera distance from the target (the thesis' SPEED+ case: 9 m)."""
    min_deg: float = 15.0
    """truth-offset: smallest rotation away from the truth (about a random axis through the target)."""
    max_deg: float = 20.0
    """truth-offset: largest rotation away from the truth."""
    shift_m: float = 0.25
    """truth-offset: distance each start is moved in a random direction; prior: largest shift per axis."""
    prior_q: tuple[float, float, float, float] | None = None
    """prior: approximate attitude of the first frame, SHIRT's q_vbs2tango (scalar first)."""
    prior_r: tuple[float, float, float] | None = None
    """prior: approximate target position in the camera frame of the first frame (metres)."""


@dataclass
class RenderConfig:
    """How candidate rays are sampled during inversion (the model's own settings are for whole scenes)."""

    bound: bool = True
    """Sample rays only where they cross a sphere about --target that holds the whole object; rays that miss
    it are background, not rendered, and fewer samples keep the renders as sharp (docs/benchmarks.md).
    Off: the model's own near and far."""
    target_radius_m: float | None = None
    """Radius of that sphere (dataset metres). Unset: read off the model's density (the object's extent
    about --target, widened by 10%)."""
    proposal_samples: tuple[int, ...] | None = None
    """Samples per ray of each proposal level (nerfacto's two levels: 64 32 when trained). Unset: 16 8 when
    rays are bounded and the model has two proposal levels, as trained otherwise."""
    nerf_samples: int | None = None
    """Samples per ray of the final field (nerfacto: 48, nerfacto-tiny: 24 when trained). Unset: 16 when rays
    are bounded and the model samples with proposals, as trained otherwise."""


@dataclass
class InvertConfig:
    """Estimate the pose of a known object in every frame of an image sequence by inverting a trained
    nerfstudio model: parallel iNeRF with Monte Carlo resampling, the observed image advancing to the next
    frame at every resampling step. Results are written as each frame finishes, so an interrupted run
    keeps them and continues with --resume."""

    load_config: Path | None = None
    """config.yml of the trained nerfstudio run (outputs/<experiment>/<method>/<timestamp>/config.yml).
    Required unless --resume is given."""
    sequence: str | None = None
    """The observed images: a SHIRT trajectory (root/roeN or root/roeN/lightbox), a Blender split
    (path/to/scene:test) or a folder of images with camera.json (and optionally poses.json). Required
    unless --resume is given."""
    preset: str | None = None
    """Settings file from configs/ (by name, such as shirt-synthetic, or by path); options given on the
    command line override it."""
    resume: Path | None = None
    """Continue the interrupted run in this folder with the settings it was started with."""
    name: str | None = None
    """Experiment name: results go to <output-dir>/<name>/nerfinv/<timestamp>/. Default: the sequence's."""
    output_dir: Path = Path("outputs")
    """Root of the results folders."""
    timestamp: str | None = None
    """Run folder name. Default: the current time, as ns-train does."""
    start: int = 0
    """First frame of the sequence to use."""
    stop: int | None = None
    """Frame to stop before (Python slice semantics). Default: the end of the sequence."""
    stride: int = 1
    """Use every stride-th frame."""
    resolution: tuple[int, int] | None = None
    """Working resolution WIDTH HEIGHT: images are resized and the intrinsics scaled to match (the thesis
    used 100 100 and 240 150). Default: the images' own size."""
    camera: Path | None = None
    """camera.json to use instead of the one found beside the sequence."""
    device: Device = "auto"
    """Where to render: cuda when available under auto."""
    seed: int = 0
    """Seeds starting poses, pixel draws and spawned candidates: same seed, same numbers on the CPU."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Target centre in the dataset frame (metres): starts look at it, and screw motions and spawned copies
    turn about it. SHIRT and SPEED+ put the body origin there."""
    starts: StartConfig = field(default_factory=StartConfig)
    bank: BankConfig = field(default_factory=BankConfig)
    masks: Path | None = None
    """Folder of object masks named like the frames (PNG, non-zero = object), used instead of finding the
    object on the dark background."""
    lost_iou: float = 0.25
    """Before each frame, the best candidate's silhouette is compared with the object found in the frame;
    below this overlap (IoU) the object counts as lost and the bank is asked again on that frame (with
    --starts.source bank). 0: never."""
    reinit_count: int = 8
    """Hypotheses the bank adds to the candidates when the object was lost."""
    watch_count: int = 2
    """Before each frame the bank also matches it (a few hundredths of a second) and its best this many
    hypotheses that are more than --watch-deg from every candidate join them, so a tracker that took a wrong
    mode (the half-turn flip of a near-symmetric object) leaves it once the bank sees the right one; the
    loss decides. With --starts.source bank. 0: never."""
    watch_deg: float = 15.0
    """How far (attitude) a bank hypothesis must be from every candidate to join them. 15 also catches a
    tracker that slid 15-30 degrees off (30 until 2026-12-02: docs/benchmarks.md, counts from nothing)."""
    reanchor: bool = True
    """Before each frame after the first, move the carried candidates' range and image position by the camera's
    motion since their frame, read off the best one's silhouette aligned with the objects found in both
    frames (attitudes unchanged; frames that cut the object too; changes of range under 2% left out): an
    approach that closes 4-10% of the range a frame otherwise leaves every candidate starting too far, and
    the frames that cut the object at its end lost it (nerfinv_plugin/inversion/reanchor.py). Uses no label;
    on by default since 2026-12-03 (docs/benchmarks.md)."""
    steps_per_frame: int = 1
    """Monte Carlo steps spent on each frame before moving to the next (1: the thesis' trajectory method)."""
    clock: ClockMode = "frames"
    """frames: every frame gets its steps in turn, however long they take; realtime: the camera does not wait
    (thesis chapter 1): after a frame's steps the next step takes the newest frame observed by then (waiting
    for one when none is new), all compute charged to the clock (bank, matching, optimisation); the frames
    skipped get poses interpolated on SE(3) between their neighbours' estimates. Needs timestamps: SHIRT's
    metadata.json, or --frame-interval-s."""
    clock_speed: float = 1.0
    """The clock advances by compute time divided by this: 0.1 simulates a computer ten times slower."""
    clock_cost_s: float | None = None
    """Charge this fixed time per optimizer iteration (and nothing else) instead of the compute time measured:
    the schedule then depends on the settings alone, the same on any machine and after --resume (tests)."""
    frame_interval_s: float | None = None
    """Seconds between consecutive frames of the sequence. Unset: SHIRT's metadata.json (pSim.cam_step, 5 s);
    other layouts then have no timestamps (and no latency)."""
    sampling: Strategy = "random"
    """Which pixels are rendered: random, interest_point (SIFT keypoints) or interest_region (5x5 around
    them, the thesis' best; random about the object by default since 2026-12-02: docs/benchmarks.md)."""
    sample_region: Region = "object"
    """Where each iteration's pixels are drawn: object: in the box of the object found in the frame, widened
    by a quarter of its size on every side (as the ranking pixels; the whole image where no object is
    found); image: anywhere (the thesis). Gauss-Newton always draws about the object."""
    pixels: int = 128
    """Pixels rendered per candidate and iteration (besides the silhouette's band pixels). 128 since
    2026-12-04 (256 before): on unseen seed-23 scenes 39 of 45 runs ended under 5 degrees against 37, at 0.70x
    the time per frame (docs/benchmarks.md, session 17); the presets keep the thesis' 256."""
    eval_pixels: int = 1024
    """Fixed random pixels per frame on which candidates are ranked."""
    rank_region: Region = "object"
    """Where those pixels are drawn: object: in the box of the object found in the frame, widened by a
    quarter of its size on every side (most pixels then tell candidates apart); image: anywhere (the
    thesis; on a small object most pixels are background)."""
    render: RenderConfig = field(default_factory=RenderConfig)
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    monte_carlo: MonteCarloConfig = field(default_factory=MonteCarloConfig)
    viewer: bool = False
    """Watch the run in nerfstudio's viewer (viser) while it goes: training cameras, the observed frame, the
    candidates coloured by loss, the kept ones, the trajectory and the model at the best candidate
    (docs/viewer.md). The URL is printed at start; the run goes on whether a browser connects or not. The
    viewer options are a front end's: a resumed run takes them from its own command line."""
    viewer_port: int | None = None
    """Port of the viewer. Default: 7007, or a free port when it is taken, as ns-train does."""
    viewer_render: bool = True
    """With --viewer: render the model at the best candidate after every step, beside the observed image (a
    160-pixel-wide image: 0.03 s a step on the toy model)."""


def to_dict(config: Any) -> dict:
    """Plain YAML-safe data (paths as strings, tuples as lists)."""
    def plain(value: Any) -> Any:
        if isinstance(value, Path):
            return str(value)
        if isinstance(value, (tuple, list)):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value
    return plain(dataclasses.asdict(config))


def _convert(hint: Any, value: Any, key: str) -> Any:
    """``value`` read from YAML as the type ``hint`` expects, checking Literal choices."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _convert(next(a for a in args if a is not type(None)), value, key)
    if origin is Literal:
        if value not in args:
            raise SettingsError(f"{key} must be one of {', '.join(map(str, args))}, not {value!r}")
        return value
    if hint is Path:
        return Path(value)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise SettingsError(f"{key} must be a list, not {value!r}")
        if args[-1] is Ellipsis:
            return tuple(_convert(args[0], v, key) for v in value)
        if len(value) != len(args):
            raise SettingsError(f"{key} needs {len(args)} values, not {len(value)}")
        return tuple(_convert(a, v, key) for a, v in zip(args, value))
    if hint is float and isinstance(value, int):
        return float(value)
    return value


def updated(config: Any, data: dict, where: str, prefix: str = "") -> Any:
    """A copy of the dataclass ``config`` with the (nested) values of ``data`` replacing its fields."""
    if not isinstance(data, dict):
        raise SettingsError(f"{where}: expected a mapping of option names for '{prefix or 'the top level'}'")
    hints = get_type_hints(type(config))
    changes = {}
    for key, value in data.items():
        name = key.replace("-", "_")
        if name not in hints:
            raise SettingsError(f"{where}: unknown option '{prefix}{key}' (see ns-invert --help)")
        current = getattr(config, name)
        if dataclasses.is_dataclass(current):
            changes[name] = updated(current, value or {}, where, f"{prefix}{key}.")
        else:
            changes[name] = _convert(hints[name], value, f"{where}: {prefix}{key}")
    return dataclasses.replace(config, **changes)


def read_yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise SettingsError(f"cannot read settings file {path}: {err}".splitlines()[0]) from err
    return data or {}


def presets_dir() -> Path:
    """The presets, ``configs/`` of the repository: the package's ``configs`` is a link to it, and a wheel
    (a non-editable install) carries the files themselves there."""
    return Path(__file__).resolve().parents[1] / "configs"


def preset_path(name: str) -> Path:
    """A preset by path, or by name in ``configs/``."""
    path = Path(name)
    if path.is_file():
        return path
    candidate = presets_dir() / f"{name}.yml"
    if candidate.is_file():
        return candidate
    known = sorted(p.stem for p in presets_dir().glob("*.yml"))
    raise SettingsError(f"no preset '{name}': give a YAML file or one of {', '.join(known) or '(none found)'}")


def preset_from_argv(argv: list[str]) -> str | None:
    """The value of ``--preset`` on a command line, read before tyro parses the rest (the preset decides
    the defaults that tyro shows and fills in)."""
    for i, arg in enumerate(argv):
        if arg == "--preset" and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith("--preset="):
            return arg.split("=", 1)[1]
    return None


def defaults_with_preset(argv: list[str] | None = None) -> InvertConfig:
    """Default settings, with the preset named on the command line applied and its values checked."""
    name = preset_from_argv(sys.argv[1:] if argv is None else argv)
    config = InvertConfig()
    if name is None:
        return config
    path = preset_path(name)
    config = dataclasses.replace(updated(config, read_yaml(path), str(path)), preset=name)
    validate(config, str(path))
    return config


def write_config(path: Path, config: InvertConfig) -> None:
    path.write_text(yaml.safe_dump(to_dict(config), sort_keys=False))


def read_config(path: Path) -> InvertConfig:
    """A run's saved settings (or any settings file), with its values checked."""
    config = updated(InvertConfig(), read_yaml(path), str(path))
    validate(config, str(path))
    return config
