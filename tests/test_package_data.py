"""Files the package needs at run time travel with it: a non-editable install finds the presets."""

from pathlib import Path

import pytest

from nerfinv_plugin.inversion.settings import preset_path, presets_dir

ROOT = Path(__file__).resolve().parents[1]


def test_the_presets_are_the_top_level_configs_and_ship_as_package_data():
    """``nerfinv_plugin/configs`` is ``configs/`` (a link), and pyproject's package data names every file
    in it, so a wheel carries every preset and grid (checked by hand with ``pip install --target``)."""
    tomllib = pytest.importorskip("tomllib")
    assert presets_dir() == ROOT / "nerfinv_plugin" / "configs"
    assert presets_dir().resolve() == (ROOT / "configs").resolve()
    assert preset_path("toy") == presets_dir() / "toy.yml"
    package_data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    shipped = {path for pattern in package_data["nerfinv_plugin"] for path in (ROOT / "nerfinv_plugin").glob(pattern)}
    in_configs = {ROOT / "nerfinv_plugin" / "configs" / p.relative_to(ROOT / "configs")
                  for p in (ROOT / "configs").rglob("*") if p.is_file()}
    assert shipped == in_configs and len(shipped) >= 4 + 6  # the presets and the thesis grids
