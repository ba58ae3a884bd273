"""The lightbox-like domain of SHIRT trajectories: the same poses as the synthetic domain, lit as a lab lights
its mock-up (:mod:`~nerfinv_plugin.synth.lab_scene`) and seen through a lab camera
(:mod:`~nerfinv_plugin.synth.lightbox`), written where SHIRT keeps its lightbox images::

    <out>/shirt/roeN/lightbox/images/img000001.jpg ...

SHIRT shares one label file per trajectory between its domains, so ``roeN.json`` (written with the
synthetic domain) labels these images too and is not touched. A simulation of a hardware-in-the-loop
facility, not the facility: no real lamp, mock-up or camera was measured.
"""

from collections.abc import Sequence
from pathlib import Path

import mitsuba as mi
import numpy as np

from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.synth.datasets import SPEEDPLUS_DIST_COEFFS, Progress, RenderedTrajectory
from nerfinv_plugin.synth.lab_scene import lab_scene, render_linear
from nerfinv_plugin.synth.lightbox import LIGHTBOX, LabCamera, degrade, encode_jpeg
from nerfinv_plugin.synth.render import PinholeCamera, distort_image, distortion_padding
from nerfinv_plugin.synth.scenes import SceneName


def lightbox_image_path(out: Path, trajectory: str, filename: str) -> Path:
    """Where SHIRT keeps the lightbox image ``filename`` of ``trajectory``."""
    return out / "shirt" / trajectory / "lightbox" / "images" / filename


def lab_frame(scene: mi.Scene, c2w_cv: np.ndarray, camera: PinholeCamera, distortion: bool, spp: int,
              render_seed: int, noise: np.random.Generator, lab_camera: LabCamera = LIGHTBOX) -> np.ndarray:
    """One lightbox frame, RGB ``uint8`` [H, W, 3] before JPEG: the linear render of the lab scene, through
    the SPEED+ lens distortion when ``distortion`` (the lens's geometry, before its blur), then degraded."""
    if distortion:
        canvas = camera.padded(*distortion_padding(camera, SPEEDPLUS_DIST_COEFFS))
        linear, _ = render_linear(scene, c2w_cv, canvas, spp, render_seed)
        linear = distort_image(linear, canvas, camera, SPEEDPLUS_DIST_COEFFS)
    else:
        linear, _ = render_linear(scene, c2w_cv, camera, spp, render_seed)
    return degrade(linear, noise, lab_camera)


def write_lightbox_domain(out: Path, scene_name: SceneName, trajectories: Sequence[RenderedTrajectory],
                          camera: PinholeCamera, distortion: bool, seed: int, spp: int,
                          step: Progress) -> list[RenderedTrajectory]:
    """Render the lightbox domain of ``trajectories`` (what
    :func:`~nerfinv_plugin.synth.datasets.write_shirt_trajectories` returned for the same ``out``,
    ``scene_name``, ``camera``, ``distortion``, ``seed``; in its order) and write each frame as a JPEG under
    the same file name as its synthetic image. The render noise uses the synthetic frame's seed, the camera
    noise the generator's ``seed`` with the trajectory's index and the frame's, so the files are the same
    for the same inputs. Returns the trajectories with the lightbox image paths."""
    scene = mi.load_dict(lab_scene(scene_name, seed))
    written = []
    for index, trajectory in enumerate(trajectories):
        paths = []
        for k, (c2w_cv, synthetic) in enumerate(zip(trajectory.c2w_opencv, trajectory.image_paths)):
            noise = np.random.default_rng([seed, index, k])
            rgb = lab_frame(scene, c2w_cv, camera, distortion, spp, seed * 7919 + index * 100_003 + k, noise)
            path = lightbox_image_path(out, trajectory.name, synthetic.name)
            write_atomic(path, encode_jpeg(rgb))
            paths.append(path)
            step()
        written.append(RenderedTrajectory(trajectory.name, trajectory.c2w_opencv, paths))
    return written
