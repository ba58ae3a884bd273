"""What every numeric option accepts, checked where settings are built (the command line, a preset, a run's
``config.yml``), so that a value the run cannot use ends the command with one line naming the option, before
anything is loaded or written, instead of a traceback deep in a run or a run that silently does nothing.

The rules live in tables keyed by the dotted option name as the user types it (``monte-carlo.keep``);
:func:`numeric_options` walks a settings tree, so a test can require a rule for every numeric field."""

import dataclasses
import math
import types
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Union, get_args, get_origin, get_type_hints

if TYPE_CHECKING:
    from nerfinv_plugin.inversion.settings import InvertConfig


class SettingsError(Exception):
    """A preset, saved config or option value that cannot be used; the message says which and why.

    Defined here rather than in settings.py (which re-exports it) because settings.py calls :func:`validate`."""


@dataclass(frozen=True)
class Rule:
    """What one option accepts, in words that complete '--option must be ...', and the test itself."""

    one: str
    """For a single value: 'a whole number of at least 1'."""
    many: str
    """For each value of a tuple: 'whole numbers of at least 1'."""
    test: Callable[[Any], bool]


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def whole(minimum: int) -> Rule:
    """An integer of at least ``minimum``."""
    return Rule(f"a whole number of at least {minimum}", f"whole numbers of at least {minimum}",
                lambda v: _is_int(v) and v >= minimum)


def number(*, above: float | None = None, at_least: float | None = None, below: float | None = None,
           at_most: float | None = None) -> Rule:
    """A finite number (never NaN or infinite) within the bounds given."""
    limits = (("above", above), ("of at least", at_least), ("below", below), ("at most", at_most))
    words = [f"{text} {limit:g}" for text, limit in limits if limit is not None]
    if at_least is not None and at_most is not None:
        words = [f"from {at_least:g} to {at_most:g}"]
    bound = f" {' and '.join(words)}" if words else ""

    def test(v: Any) -> bool:
        return _is_finite(v) and (above is None or v > above) and (at_least is None or v >= at_least) and \
            (below is None or v < below) and (at_most is None or v <= at_most)

    return Rule(f"a finite number{bound}", f"finite numbers{bound}", test)


def several(each: Rule, count: int | None = None, empty: bool = False) -> Rule:
    """A tuple of values that each pass ``each``: exactly ``count`` of them, else one or more (or none, with
    ``empty``)."""
    if count is not None:
        words = f"{count} {each.many}"
    else:
        words = f"{each.many} (or none)" if empty else f"one or more {each.many}"

    def test(v: Any) -> bool:
        if not isinstance(v, (tuple, list)):
            return False
        sized = len(v) == count if count is not None else empty or len(v) > 0
        return sized and all(each.test(x) for x in v)

    return Rule(words, words, test)


_FOUR_NUMBERS = several(number(), 4)
QUATERNION = Rule("4 finite numbers of non-zero length (a quaternion)", "quaternions",
                  lambda v: _FOUR_NUMBERS.test(v) and any(x != 0 for x in v))
"""A scalar-first quaternion of any length but 0 (it is normalized where it is used)."""
PORT = Rule("a whole number from 1 to 65535 (a TCP port)", "TCP ports", lambda v: _is_int(v) and 1 <= v <= 65535)


def under(prefix: str, rules: Mapping[str, Rule]) -> dict[str, Rule]:
    """``rules`` for the options of a dataclass nested under ``prefix`` (``training-set``)."""
    return {f"{prefix}.{name}": rule for name, rule in rules.items()}


INVERT_RULES: dict[str, Rule] = {
    "start": whole(0),
    "stop": whole(0),  # read_sequence refuses a negative stop, so no end-relative -1 here
    "stride": whole(1),
    "resolution": several(whole(1), 2),
    "seed": whole(0),  # numpy's generators take no negative seed
    "target": several(number(), 3),
    "lost-iou": number(at_least=0, at_most=1),  # 0: never ask the bank again
    "reinit-count": whole(1),  # turning re-initialization off is --lost-iou 0
    "watch-count": whole(0),  # 0: the bank does not watch the frames
    "watch-deg": number(at_least=0, at_most=180),
    "steps-per-frame": whole(1),
    "clock-speed": number(above=0),
    "clock-cost-s": number(above=0),
    "frame-interval-s": number(above=0),
    "pixels": whole(1),
    "eval-pixels": whole(1),
    "starts.count": whole(1),
    "starts.range-m": number(above=0),
    "starts.min-range-m": number(above=0),
    "starts.max-range-m": number(above=0),
    "starts.min-deg": number(at_least=0, at_most=180),
    "starts.max-deg": number(at_least=0, at_most=180),
    "starts.shift-m": number(at_least=0),
    "starts.prior-q": QUATERNION,
    "starts.prior-r": several(number(), 3),
    "render.target-radius-m": number(above=0),
    "render.proposal-samples": several(whole(1)),
    "render.nerf-samples": whole(1),
    "bank.subdivisions": whole(0),  # 0: the icosahedron's 12 vertices
    "bank.in-plane": whole(1),
    "bank.render-px": whole(1),
    "bank.crop-px": whole(1),
    "bank.range-radii": number(above=1),  # the cameras stay outside the object's bounding sphere
    "bank.silhouette-weight": number(at_least=0, at_most=1),
    "bank.nms-deg": number(at_least=0, at_most=180),
    "bank.batch-views": whole(1),
    "optimizer.iterations": whole(1),
    "optimizer.gauss-newton-iterations": whole(1),
    "optimizer.gauss-newton-blur-px": several(number(at_least=0)),
    "optimizer.gauss-newton-rays-per-pixel": whole(1),
    "optimizer.lr": number(above=0),
    "optimizer.colour-weight": number(at_least=0),
    "optimizer.silhouette-weight": number(at_least=0),
    "optimizer.rank-silhouette-weight": number(at_least=0),
    "optimizer.silhouette-trust": number(above=0),
    "optimizer.silhouette-pixels": whole(1),
    "optimizer.silhouette-band-px": whole(1),
    "optimizer.silhouette-softness": number(above=0),
    "optimizer.silhouette-edge": number(at_least=0, below=1),  # 1 would cut at the median: half the object
    "optimizer.lr-decay": number(above=0, at_most=1),
    "optimizer.lr-decay-iterations": whole(1),
    "optimizer.averaging": number(at_least=0, below=1),  # 1 would never leave the start
    "optimizer.patience": whole(1),
    "optimizer.min-improvement": number(at_least=0, below=1),  # 1 would ask for a loss of 0
    "optimizer.prune-every": whole(1),
    "optimizer.prune-ratio": number(at_least=1),  # below 1 even the best candidate is far above the best
    "optimizer.polish-iterations": whole(0),  # 0: off
    "optimizer.polish-pixels": whole(1),
    "optimizer.polish-lr": number(above=0),
    "monte-carlo.keep": several(whole(1)),
    "monte-carlo.keep-fraction": number(above=0, at_most=1),
    "monte-carlo.spawn": whole(0),  # 0: the kept candidates go on alone
    "monte-carlo.spawn-rot-deg": number(at_least=0, at_most=180),
    "monte-carlo.spawn-trans-m": number(at_least=0),
    # the filter's noises are standard deviations of Gaussians: 0 would make a covariance singular
    "monte-carlo.motion-filter.measurement-deg": number(above=0, at_most=180),
    "monte-carlo.motion-filter.measurement-m": number(above=0),
    "monte-carlo.motion-filter.accel-deg": number(above=0, at_most=180),
    "monte-carlo.motion-filter.accel-m": number(above=0),
    "monte-carlo.motion-filter.initial-rate-deg": number(above=0, at_most=180),
    "monte-carlo.motion-filter.initial-speed-m": number(above=0),
    "monte-carlo.motion-filter.gate-probability": number(above=0, below=1),  # 1: an infinite gate
    "monte-carlo.motion-filter.max-rejections": whole(1),  # 0 would restart on every outlier: no gate at all
    "viewer-port": PORT,
}
"""The rule of every numeric option of ``ns-invert`` (:class:`InvertConfig` and the configs nested in it)."""


def _without_none(hint: Any) -> tuple[Any, bool]:
    """``hint`` with ``None`` taken out of a union, and whether it was there (the option may be unset)."""
    if get_origin(hint) in (Union, types.UnionType):
        args = tuple(a for a in get_args(hint) if a is not type(None))
        return (args[0] if len(args) == 1 else hint), len(args) < len(get_args(hint))
    return hint, False


def _is_numeric(hint: Any) -> bool:
    """int, float, or a tuple of them (bool is not numeric here: it is a switch)."""
    hint, _ = _without_none(hint)
    if get_origin(hint) is tuple:
        return all(a in (int, float) for a in get_args(hint) if a is not Ellipsis)
    return hint in (int, float)


def numeric_options(config_type: type, prefix: str = "") -> dict[str, Any]:
    """Every numeric option of the dataclass ``config_type`` and the dataclasses nested in it: dotted name as
    typed on the command line (``monte-carlo.keep``) to the field's type hint."""
    hints = get_type_hints(config_type)
    options = {}
    for f in dataclasses.fields(config_type):
        name = prefix + f.name.replace("_", "-")
        if dataclasses.is_dataclass(hints[f.name]):
            options.update(numeric_options(hints[f.name], f"{name}."))
        elif _is_numeric(hints[f.name]):
            options[name] = hints[f.name]
    return options


def uncovered(config_type: type, rules: Mapping[str, Rule]) -> list[str]:
    """Numeric options of ``config_type`` without a rule, and rules that name no option (a field renamed)."""
    options = numeric_options(config_type)
    return sorted(set(options) ^ set(rules))


def _value(config: Any, name: str) -> Any:
    for part in name.split("."):
        config = getattr(config, part.replace("-", "_"))
    return config


def _shown(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return " ".join(map(_shown, value)) if value else "an empty list"
    return str(value) if _is_int(value) or isinstance(value, float) else repr(value)


def _option(name: str, where: str | None) -> str:
    """An option as a message names it: typed on the command line (``--optimizer.lr``), or as a key of the
    file ``where`` it was read from."""
    return f"{where}: {name}" if where else f"--{name}"


def check(config: Any, rules: Mapping[str, Rule], where: str | None = None) -> None:
    """Raise :class:`SettingsError` for the first numeric option of ``config`` that breaks its rule. The message
    names it as typed on the command line (``--optimizer.lr``), or as a key of the file ``where`` it was read
    from. Unset is always allowed where the field's type is optional. An option without a rule is not checked
    here (a run should not fail for it): the tests require a rule for every option."""
    for name, hint in numeric_options(type(config)).items():
        value = _value(config, name)
        rule = rules.get(name)
        if rule is None or (value is None and _without_none(hint)[1]) or rule.test(value):
            continue
        option = _option(name, where)
        raise SettingsError(f"{option} must be {rule.one}, not {_shown(value)}")


def validate(config: "InvertConfig", where: str | None = None) -> None:
    """Check every numeric option of an ``ns-invert`` configuration against :data:`INVERT_RULES`; ``where``
    names the file it was read from, if any."""
    check(config, INVERT_RULES, where)
    optimizer = config.optimizer
    if optimizer.colour_weight == 0 and optimizer.silhouette_weight == 0:
        option = _option("optimizer.colour-weight", where)
        raise SettingsError(f"{option} must be above 0 when the silhouette weight is 0 (the loss would be 0 and "
                            "nothing would move): give --optimizer.silhouette-weight too")
    if optimizer.colour_weight == 0 and optimizer.rank_silhouette_weight == 0:  # unset follows the weight above
        option = _option("optimizer.colour-weight", where)
        raise SettingsError(f"{option} must be above 0 when the ranking's silhouette weight is 0 (every candidate "
                            "would rank the same): give --optimizer.rank-silhouette-weight too")
    if optimizer.method == "gauss-newton":
        name = _option("optimizer.method", where)
        if optimizer.loss != "mse" or optimizer.silhouette_weight > 0 or optimizer.colour_weight != 1:
            raise SettingsError(f"{name} gauss-newton fits the mean squared colour error alone: leave --optimizer.loss "
                                "mse, --optimizer.silhouette-weight 0 and --optimizer.colour-weight 1, or use "
                                "--optimizer.method adam")
        if optimizer.appearance == "candidate-gain-bias":
            raise SettingsError(f"{name} gauss-newton compares one mapping of the frame for all candidates: use "
                                "--optimizer.appearance gain-bias or as-observed with it, or --optimizer.method adam")
