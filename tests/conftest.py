"""Session fixtures: a small synthetic scene and a nerfacto-tiny trained on it on the CPU.

Training takes minutes, so the run is cached under ``$NERFINV_TEST_CACHE`` (default
``~/.cache/nerfinv/tests``) in a folder named by a hash of everything that determines it: the scene and
training settings, the source of the code that renders and trains, and the versions of nerfstudio, torch
and mitsuba. Change any of them and the fixture trains afresh; delete the folder to force it.
"""

import fcntl
import hashlib
import json
import os
import shutil
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path

import pytest

from nerfinv_plugin.synth.datasets import TrainingSetSpec, write_training_set

PACKAGE = Path(__file__).resolve().parents[1] / "nerfinv_plugin"

TOY_SCENE = {"scene": "toy", "seed": 0, "spp": 64,
             "spec": TrainingSetSpec(train_views=60, val_views=4, test_views=6, width=80, height=50)}
TOY_TRAINING = {"iterations": 1000, "rays_per_batch": 512}


TOY_RGB_TRAINING = {**TOY_TRAINING, "dataparser": "nerfstudio-data"}
"""The same scene as a camera delivers it (RGB JPEG over black, no alpha), trained through nerfstudio-data
with its defaults: the way users train."""

TRAINING_SOURCES = ("synth/scenes.py", "synth/render.py", "synth/trajectories.py", "synth/datasets.py",
                    "synth/camera_images.py", "geometry/frames.py", "model/nerfacto_tiny.py", "model/fused_hash.py",
                    "model/training.py", "model/opacity.py", "initialization/detect.py")
"""The code whose behaviour determines the trained fixture (rendering the data and training on it)."""


def cache_root() -> Path:
    return Path(os.environ.get("NERFINV_TEST_CACHE", Path.home() / ".cache" / "nerfinv" / "tests"))


def cache_key(*settings: object) -> str:
    digest = hashlib.sha256()
    digest.update(json.dumps([repr(s) for s in settings]).encode())
    for package in ("nerfstudio", "torch", "mitsuba"):
        digest.update(version(package).encode())
    for source in TRAINING_SOURCES:
        digest.update((PACKAGE / source).read_bytes())
    return digest.hexdigest()[:16]


def _noop() -> None:
    pass


def _build_toy_run(folder: Path) -> Path:
    from nerfinv_plugin.model.training import train_nerfacto_tiny

    data = folder / "data"
    write_training_set(data, TOY_SCENE["scene"], TOY_SCENE["spec"], TOY_SCENE["seed"], TOY_SCENE["spp"], _noop)
    return train_nerfacto_tiny(data, folder / "outputs", "toy", TOY_TRAINING["iterations"],
                               TOY_TRAINING["rays_per_batch"], timestamp="fixture")


def _build_toy_rgb_run(folder: Path) -> Path:
    from nerfinv_plugin.model.training import train_nerfacto_tiny
    from nerfinv_plugin.synth.camera_images import write_camera_images

    data = folder / "data"
    write_training_set(data, TOY_SCENE["scene"], TOY_SCENE["spec"], TOY_SCENE["seed"], TOY_SCENE["spp"], _noop)
    write_camera_images(data, folder / "rgb")
    return train_nerfacto_tiny(folder / "rgb", folder / "outputs", "toy-rgb", TOY_RGB_TRAINING["iterations"],
                               TOY_RGB_TRAINING["rays_per_batch"], timestamp="fixture",
                               dataparser=TOY_RGB_TRAINING["dataparser"])


def _cached_run(name: str, settings: tuple, build: Callable[[Path], Path], experiment: str) -> tuple[Path, Path]:
    """``(config.yml, data folder)`` of a run built by ``build`` once per cache key."""
    folder = cache_root() / f"{name}-{cache_key(*settings)}"
    config = folder / "outputs" / experiment / "nerfacto-tiny" / "fixture" / "config.yml"
    folder.parent.mkdir(parents=True, exist_ok=True)
    # Test sessions running side by side must not build (and delete) the same folder at once.
    with open(folder.parent / f"{folder.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (folder / "complete").is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            assert build(folder) == config
            (folder / "complete").write_text("trained\n")
    return config, folder / "data"


@pytest.fixture(scope="session")
def toy_run() -> tuple[Path, Path]:
    """``(config.yml, data folder)`` of nerfacto-tiny trained on the toy scene, cached across sessions."""
    return _cached_run("toy", (TOY_SCENE, TOY_TRAINING), _build_toy_run, "toy")


@pytest.fixture(scope="session")
def toy_rgb_run() -> tuple[Path, Path]:
    """``(config.yml, data folder)`` of nerfacto-tiny trained the way users train: the toy scene's RGB
    images without alpha through nerfstudio-data; the data folder holds the RGBA originals and their Blender
    splits, for scoring on the same held-out views as :func:`toy_run`."""
    return _cached_run("toy-rgb", (TOY_SCENE, TOY_RGB_TRAINING), _build_toy_rgb_run, "toy-rgb")


@pytest.fixture(scope="session")
def toy_held_out(toy_run):
    """The toy model loaded on the CPU, the intrinsics and true pose (model frame) of its first held-out
    view, read with the project's Blender reader, and the target centre (the dataset origin) in the model
    frame: a camera to render the model from where the answer is known."""
    import numpy as np
    import torch

    from nerfinv_plugin.data.sequences import read_sequence
    from nerfinv_plugin.model.loading import load_model

    config, data = toy_run
    loaded = load_model(config, device="cpu")
    sequence = read_sequence(f"{data}:test", 0, 1)
    truth = torch.as_tensor(loaded.dataset_to_model(sequence.frames[0].c2w_true), dtype=torch.float32)
    centre = torch.as_tensor(loaded.dataset_to_model(np.eye(4))[:3, 3], dtype=torch.float32)
    return loaded, sequence.intrinsics, truth, centre
