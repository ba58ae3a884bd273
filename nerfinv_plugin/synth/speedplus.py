"""Rendered views written in the SPEED+ layout, so that ``speedplus-data`` is tested and demonstrated on
real files (SPEED+ itself cannot be downloaded here)::

    <out>/camera.json
    <out>/synthetic/train.json           [{"filename", "q_vbs2tango_true", "r_Vo2To_vbs_true"}, ...]
    <out>/synthetic/validation.json
    <out>/synthetic/images/img000001.jpg ...   train first, then validation, in one folder as in SPEED+

Images are RGB JPEG over black, as a camera records them; with ``distortion`` they pass through the
SPEED+ lens model that camera.json then carries.
"""

import json
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from nerfinv_plugin.geometry.frames import c2w_opencv_to_label
from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.synth.datasets import (
    SPEEDPLUS_DIST_COEFFS,
    Progress,
    camera_json,
    speedplus_like_camera,
    write_image,
)
from nerfinv_plugin.synth.render import PinholeCamera, distort_image, distortion_padding, render_view
from nerfinv_plugin.synth.scenes import SCENE_CENTRES, SceneName, build_scene
from nerfinv_plugin.synth.trajectories import orbit_views

SPLITS = ("train", "validation")


@dataclass(frozen=True)
class RenderedSpeedPlus:
    """What was rendered: the ground truth that the written labels, and a dataparser, must give back."""

    camera: PinholeCamera
    dist_coeffs: np.ndarray
    """OpenCV (k1, k2, p1, p2, k3) written to camera.json (zeros without distortion)."""
    filenames: dict[str, list[str]]
    """Image filenames per split ("train", "validation")."""
    c2w_opencv: dict[str, np.ndarray]
    """[N, 4, 4] camera-to-body poses (OpenCV camera axes, metres) per split, in label order."""


def label_of(filename: str, c2w_cv: np.ndarray) -> dict:
    """The SPEED+ label of a camera pose: the body in the camera frame, ``X_cam = R X_body + r``."""
    q, r = c2w_opencv_to_label(c2w_cv)
    return {"filename": filename, "q_vbs2tango_true": q.tolist(), "r_Vo2To_vbs_true": r.tolist()}


def write_speedplus(out: Path, scene_name: SceneName, train: int, validation: int, width: int, height: int,
                    distortion: bool, seed: int, spp: int, step: Progress, range_m: float = 5.0,
                    range_jitter: float = 0.2) -> RenderedSpeedPlus:
    """Render ``train + validation`` views spread over the sphere around the object (shuffled, so both
    splits see every side) at ``range_m * (1 +- range_jitter)`` metres, into a SPEED+ root at ``out``."""
    if train < 1 or validation < 1:
        raise ValueError(f"a SPEED+ tree needs train and validation views (nerfstudio evaluates on "
                         f"validation.json), got train={train}, validation={validation}")
    scene = mi.load_dict(build_scene(scene_name, seed))
    camera = speedplus_like_camera(width, height)
    dist = SPEEDPLUS_DIST_COEFFS if distortion else np.zeros(5)
    canvas = camera.padded(*distortion_padding(camera, dist)) if distortion else camera
    rng = np.random.default_rng(seed)
    poses = orbit_views(train + validation, range_m, range_jitter, SCENE_CENTRES[scene_name], rng)
    rng.shuffle(poses)
    write_atomic(out / "camera.json", json.dumps(camera_json(camera, dist), indent=2))
    filenames, split_poses, start = {}, {}, 0
    for split, count in zip(SPLITS, (train, validation)):
        names = [f"img{start + k + 1:06d}.jpg" for k in range(count)]
        for k, name in enumerate(names):
            rgb, _ = render_view(scene, poses[start + k], canvas, spp, seed=seed * 7919 + start + k)
            if distortion:
                rgb = distort_image(rgb, canvas, camera, dist)
            write_image(out / "synthetic" / "images" / name, rgb)
            step()
        labels = [label_of(name, pose) for name, pose in zip(names, poses[start:start + count])]
        write_atomic(out / "synthetic" / f"{split}.json", json.dumps(labels, indent=2))
        filenames[split], split_poses[split] = names, poses[start:start + count]
        start += count
    return RenderedSpeedPlus(camera, dist, filenames, split_poses)
