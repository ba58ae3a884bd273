"""Every numeric option is checked where settings are built: a value a run cannot use ends the command with
one line that names the option, with exit code 2, before anything is loaded or written."""

import math
import os
import shutil
import subprocess
import types
from dataclasses import replace
from pathlib import Path
from typing import Any, Union, get_args, get_origin

import pytest

from nerfinv_plugin.cli.demo import RULES as DEMO_RULES
from nerfinv_plugin.cli.demo import Demo
from nerfinv_plugin.cli.psnr import RULES as PSNR_RULES
from nerfinv_plugin.cli.psnr import HeldOutPSNR
from nerfinv_plugin.cli.report import RULES as REPORT_RULES
from nerfinv_plugin.cli.report import ReportCommand
from nerfinv_plugin.cli.synth import RULES as SYNTH_RULES
from nerfinv_plugin.cli.synth import Synth
from nerfinv_plugin.inversion.settings import InvertConfig, SettingsError, defaults_with_preset, read_config
from nerfinv_plugin.inversion.validation import INVERT_RULES, check, numeric_options, uncovered, validate

ACCEPTED = {
    "start": {0}, "stop": {0}, "seed": {0}, "target": {0, -1}, "lost-iou": {0}, "watch-count": {0}, "watch-deg": {0},
    "starts.min-deg": {0}, "starts.max-deg": {0}, "starts.shift-m": {0}, "starts.prior-q": {-1},
    "starts.prior-r": {0, -1}, "bank.subdivisions": {0}, "bank.silhouette-weight": {0}, "bank.nms-deg": {0},
    "optimizer.silhouette-weight": {0}, "optimizer.rank-silhouette-weight": {0},
    "optimizer.colour-weight": {0},  # not with a silhouette weight 0: the cross-check below
    "optimizer.min-improvement": {0}, "monte-carlo.spawn": {0}, "monte-carlo.spawn-rot-deg": {0},
    "monte-carlo.spawn-trans-m": {0}, "optimizer.gauss-newton-blur-px": {0},  # 0 px: the sharp level
    "optimizer.averaging": {0},  # 0: off
    "optimizer.polish-iterations": {0},  # 0: off
    "optimizer.silhouette-edge": {0},  # 0: the detector's threshold
}
"""Which of 0 and -1 each ns-invert option takes (a tuple option: every entry that value); the others take
neither. No option takes NaN or infinity, and no tuple option takes an empty one."""

COMMANDS = [(InvertConfig(), INVERT_RULES), (Synth(Path("out")), SYNTH_RULES), (Demo(), DEMO_RULES),
            (HeldOutPSNR(Path("config.yml"), Path("data")), PSNR_RULES), (ReportCommand(Path("run")), REPORT_RULES)]


def _inner(hint: Any) -> Any:
    if get_origin(hint) in (Union, types.UnionType):
        return next(a for a in get_args(hint) if a is not type(None))
    return hint


def _filled(hint: Any, value: float) -> Any:
    """``value`` as the option of type ``hint`` takes it: alone, or every entry of a tuple."""
    inner = _inner(hint)
    if get_origin(inner) is not tuple:
        return value
    args = get_args(inner)
    return (value,) * (2 if args[-1] is Ellipsis else len(args))


def _replaced(config: Any, option: str, value: Any) -> Any:
    """``config`` with the dotted ``option`` (``monte-carlo.keep``) set to ``value``."""
    head, _, rest = option.partition(".")
    name = head.replace("-", "_")
    return replace(config, **{name: _replaced(getattr(config, name), rest, value) if rest else value})


def _value(config: Any, option: str) -> Any:
    """The dotted ``option`` of ``config``."""
    for part in option.split("."):
        config = getattr(config, part.replace("-", "_"))
    return config


def _cases(valid: bool) -> list[Any]:
    cases = []
    for option, hint in numeric_options(InvertConfig).items():
        for value in (0, -1, math.nan, math.inf):
            if (value in ACCEPTED.get(option, set())) == valid:
                cases.append(pytest.param(option, _filled(hint, value), id=f"{option}={value}"))
        if not valid and get_origin(_inner(hint)) is tuple:
            cases.append(pytest.param(option, (), id=f"{option}=()"))
    return cases


@pytest.mark.parametrize(("option", "value"), _cases(valid=False))
def test_an_invalid_value_is_refused_in_one_line_naming_the_option(option, value):
    with pytest.raises(SettingsError) as caught:
        validate(_replaced(InvertConfig(), option, value))
    message = str(caught.value)
    assert message.startswith(f"--{option} must be ") and "\n" not in message, message


@pytest.mark.parametrize(("option", "value"), _cases(valid=True))
def test_zero_and_minus_one_pass_where_they_mean_something(option, value):
    config = _replaced(InvertConfig(), option, value)
    validate(config)  # raises SettingsError if the rule refuses the value
    assert _value(config, option) == value  # and the value validated was really the option's


def test_the_colour_weight_may_be_0_only_with_both_silhouette_weights():
    base = InvertConfig()
    alone = replace(base, optimizer=replace(base.optimizer, colour_weight=0.0, silhouette_weight=1.0))
    validate(alone)  # the ranking's weight, unset, follows the optimization's
    validate(replace(alone, optimizer=replace(alone.optimizer, rank_silhouette_weight=0.5)))
    with pytest.raises(SettingsError, match="when the silhouette weight is 0"):
        validate(replace(alone, optimizer=replace(alone.optimizer, silhouette_weight=0.0)))
    with pytest.raises(SettingsError, match="when the ranking's silhouette weight is 0"):
        validate(replace(alone, optimizer=replace(alone.optimizer, rank_silhouette_weight=0.0)))


@pytest.mark.parametrize("option", [o for o, hint in numeric_options(InvertConfig).items() if _inner(hint) != hint])
def test_an_optional_option_may_stay_unset(option):
    config = _replaced(InvertConfig(), option, None)
    validate(config)  # raises SettingsError if the rule refuses None
    assert _value(config, option) is None


@pytest.mark.parametrize(("config", "rules"), COMMANDS, ids=lambda c: type(c).__name__)
def test_every_numeric_option_has_a_rule_and_the_defaults_pass(config, rules):
    assert uncovered(type(config), rules) == []
    check(config, rules)


@pytest.mark.parametrize(("config", "rules"), COMMANDS, ids=lambda c: type(c).__name__)
def test_no_option_of_any_command_takes_nan(config, rules):
    for option, hint in numeric_options(type(config)).items():
        with pytest.raises(SettingsError, match=f"^--{option} must be .*, not nan"):
            check(_replaced(config, option, _filled(hint, math.nan)), rules)


def test_the_coverage_check_sees_a_missing_rule_and_a_stale_one():
    options = numeric_options(InvertConfig)
    assert "monte-carlo.keep" in options and "starts.prior-q" in options
    assert not {"render.bound", "device", "output-dir", "sampling"} & set(options)  # switches, choices, paths
    rules = {name: rule for name, rule in INVERT_RULES.items() if name != "pixels"}
    assert uncovered(InvertConfig, {**rules, "pixel": INVERT_RULES["pixels"]}) == ["pixel", "pixels"]


@pytest.mark.parametrize(("text", "message"), [
    ("optimizer:\n  lr: .nan\n", "optimizer.lr must be a finite number above 0, not nan"),
    ("pixels: many\n", "pixels must be a whole number of at least 1, not 'many'"),
    ("pixels:\n", "pixels must be a whole number of at least 1, not None"),
    ("monte-carlo:\n  keep: [3, 0]\n", "monte-carlo.keep must be one or more whole numbers of at least 1, not 3 0"),
])
def test_a_saved_config_or_preset_is_checked_naming_its_file(tmp_path, text, message):
    path = tmp_path / "settings.yml"
    path.write_text(text)
    with pytest.raises(SettingsError) as caught:
        read_config(path)
    assert str(caught.value) == f"{path}: {message}"
    with pytest.raises(SettingsError) as caught:
        defaults_with_preset(["--preset", str(path)])
    assert str(caught.value) == f"{path}: {message}"


def test_a_preset_may_leave_an_optional_option_unset(tmp_path):
    (tmp_path / "p.yml").write_text("render:\n  target-radius-m: null\nstarts:\n  range-m: 3\n")
    assert defaults_with_preset(["--preset", str(tmp_path / "p.yml")]).starts.range_m == 3.0


def _refused(command: str, *args: str) -> str:
    """Run ``command``; it must end with exit code 2 and one line on stderr, no traceback."""
    result = subprocess.run([shutil.which(command), *args], capture_output=True, text=True, timeout=300,
                            env={**os.environ, "COLUMNS": "200"})
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    return result.stderr


@pytest.mark.parametrize(("args", "expected"), [
    (["--pixels", "0"], "--pixels must be a whole number of at least 1, not 0"),
    (["--optimizer.lr", "nan"], "--optimizer.lr must be a finite number above 0, not nan"),
    (["--optimizer.iterations", "-1"], "--optimizer.iterations must be a whole number of at least 1, not -1"),
])
def test_ns_invert_refuses_before_loading_or_writing(tmp_path, args, expected):
    missing = tmp_path / "missing"
    err = _refused("ns-invert", "--load-config", str(missing / "config.yml"), "--sequence", str(missing / "roe1"),
                   "--output-dir", str(tmp_path / "out"), *args)
    assert expected in err
    assert not (tmp_path / "out").exists()


def test_the_other_commands_refuse_before_any_work(tmp_path):
    assert "--spp must be" in _refused("ns-invert-synth", "--out", str(tmp_path / "synth"), "--spp", "0")
    assert "--max-views must be" in _refused("ns-invert-psnr", "--load-config", str(tmp_path / "config.yml"),
                                             "--data", str(tmp_path), "--max-views", "0")
    assert "--frames must be" in _refused("ns-invert-demo", "--data-dir", str(tmp_path / "data"), "--output-dir",
                                          str(tmp_path / "out"), "--frames", "0")
    assert not {"synth", "data", "out"} & {p.name for p in tmp_path.iterdir()}
