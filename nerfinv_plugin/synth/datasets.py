"""Writing rendered scenes to disk in the published formats.

- Training sets as RGBA PNGs (straight alpha, as Blender's synthetic scenes) with Blender
  ``transforms_{train,val,test}.json`` (read by ``ns-train ... blender-data``) and
  the same views as a nerfstudio ``transforms.json`` with per-split file lists (``nerfstudio-data``).
- Trajectories as SHIRT: ``shirt/camera.json``, ``shirt/roeN/roeN.json`` (labels) and
  ``shirt/roeN/synthetic/images/img000001.jpg``.
"""

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import mitsuba as mi
import numpy as np

from nerfinv_plugin.geometry.frames import object_to_camera_to_c2w, opencv_to_opengl, rotmat_to_quat_wxyz
from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.synth.render import (
    PinholeCamera,
    distort_image,
    distortion_padding,
    render_view,
    render_view_rgba,
)
from nerfinv_plugin.synth.scenes import SCENE_CENTRES, SceneName, build_scene
from nerfinv_plugin.synth.trajectories import TrajectorySpec, orbit_views, trajectory_object_to_camera

SPEEDPLUS_DIST_COEFFS = np.array([-0.22383016606510672, 0.51409797089106379, -0.00066499611998340662,
                                  -0.00021404771667484594, -0.13124227429077406])
"""OpenCV (k1, k2, p1, p2, k3) of the SPEED+ camera, applied with ``--distortion``."""

SPEEDPLUS_FOCAL_M = 0.017513075965995915
SPEEDPLUS_PIXEL_PITCH_M = 5.86e-6
SPEEDPLUS_WIDTH = 1920

Progress = Callable[[], None]


def write_json_atomic(path: Path, data: object) -> None:
    """Write ``data`` as indented JSON with the project's one atomic writer (a crash never leaves half a
    file)."""
    write_atomic(path, json.dumps(data, indent=2))


def write_image(path: Path, image: np.ndarray) -> None:
    """Write an RGB or RGBA ``uint8`` image (PNG keeps alpha; JPEG at quality 95)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix == ".jpg" else []
    code = cv2.COLOR_RGBA2BGRA if image.shape[-1] == 4 else cv2.COLOR_RGB2BGR
    if not cv2.imwrite(str(path), cv2.cvtColor(image, code), params):
        raise OSError(f"could not write image {path}")


def speedplus_like_camera(width: int, height: int) -> PinholeCamera:
    """The SPEED+ camera's field of view on a ``width`` x ``height`` sensor, principal point at the
    centre pixel as camera.json files give it (ccx = Nu / 2)."""
    focal_px = SPEEDPLUS_FOCAL_M / SPEEDPLUS_PIXEL_PITCH_M * width / SPEEDPLUS_WIDTH
    return PinholeCamera(width, height, focal_px, width / 2, height / 2)


def camera_json(camera: PinholeCamera, dist_coeffs: np.ndarray) -> dict:
    """SHIRT / SPEED+ ``camera.json``: focal lengths in metres with the pixel pitch that converts them."""
    pitch = SPEEDPLUS_FOCAL_M / camera.focal
    return {
        "Nu": camera.width, "Nv": camera.height,
        "ppx": pitch, "ppy": pitch,
        "fx": SPEEDPLUS_FOCAL_M, "fy": SPEEDPLUS_FOCAL_M,
        "ccx": camera.cx, "ccy": camera.cy,
        "cameraMatrix": camera.matrix.tolist(),
        "distCoeffs": np.asarray(dist_coeffs, dtype=np.float64).tolist(),
    }


@dataclass(frozen=True)
class TrainingSetSpec:
    """Views for training a NeRF of a scene."""

    train_views: int = 100
    """Views written to transforms_train.json."""
    val_views: int = 10
    """Views written to transforms_val.json."""
    test_views: int = 10
    """Held-out views written to transforms_test.json."""
    width: int = 120
    """Image width in pixels; the field of view is SPEED+'s (35.6 degrees across)."""
    height: int = 75
    """Image height in pixels."""
    range_m: float = 5.0
    """Camera distance from the object centre (metres)."""
    range_jitter: float = 0.1
    """Ranges are drawn from ``range_m * (1 +- range_jitter)``."""


def write_training_set(out: Path, scene_name: SceneName, spec: TrainingSetSpec, seed: int, spp: int,
                       step: Progress) -> None:
    """Render the views and write both Blender and nerfstudio transforms files under ``out``."""
    scene = mi.load_dict(build_scene(scene_name, seed))
    camera = speedplus_like_camera(spec.width, spec.height)
    # Blender's format fixes the principal point at the image centre (W/2 in continuous coordinates,
    # (W-1)/2 in OpenCV's), so render exactly that camera.
    camera = PinholeCamera(spec.width, spec.height, camera.focal, (spec.width - 1) / 2, (spec.height - 1) / 2)
    rng = np.random.default_rng(seed)
    counts = {"train": spec.train_views, "val": spec.val_views, "test": spec.test_views}
    poses = orbit_views(sum(counts.values()), spec.range_m, spec.range_jitter, SCENE_CENTRES[scene_name], rng)
    rng.shuffle(poses)  # every split spreads over the whole sphere
    nerfstudio_frames, split_files, start = [], {}, 0
    for split, count in counts.items():
        frames = []
        for i in range(count):
            c2w_cv = poses[start + i]
            rgba = render_view_rgba(scene, c2w_cv, camera, spp, seed=seed * 100_003 + start + i)
            write_image(out / split / f"r_{i:03d}.png", rgba)
            c2w_gl = opencv_to_opengl(c2w_cv).tolist()
            frames.append({"file_path": f"./{split}/r_{i:03d}", "transform_matrix": c2w_gl})
            nerfstudio_frames.append({"file_path": f"{split}/r_{i:03d}.png", "transform_matrix": c2w_gl})
            step()
        split_files[f"{split}_filenames"] = [f"{split}/r_{i:03d}.png" for i in range(count)]
        write_json_atomic(out / f"transforms_{split}.json",
                          {"camera_angle_x": np.radians(camera.fov_x_deg), "frames": frames})
        start += count
    write_json_atomic(out / "transforms.json", {
        "camera_model": "OPENCV", "w": camera.width, "h": camera.height,
        "fl_x": camera.focal, "fl_y": camera.focal, "cx": camera.width / 2, "cy": camera.height / 2,
        "frames": nerfstudio_frames, **split_files,
    })


@dataclass(frozen=True)
class RenderedTrajectory:
    """What a trajectory was rendered from: the ground truth the written labels must give back."""

    name: str
    c2w_opencv: np.ndarray
    """[F, 4, 4] camera-to-body poses used for rendering."""
    image_paths: list[Path]


def write_shirt_trajectories(out: Path, scene_name: SceneName, specs: Sequence[TrajectorySpec],
                             camera: PinholeCamera, distortion: bool, seed: int, spp: int,
                             step: Progress) -> list[RenderedTrajectory]:
    """Render trajectories into a SHIRT tree at ``out/shirt``.

    With ``distortion`` the images go through the SPEED+ lens model (camera.json carries it); without,
    they are ideal pinhole images and camera.json says so with zero coefficients.
    """
    scene = mi.load_dict(build_scene(scene_name, seed))
    dist = SPEEDPLUS_DIST_COEFFS if distortion else np.zeros(5)
    root = out / "shirt"
    write_json_atomic(root / "camera.json", camera_json(camera, dist))
    canvas = camera.padded(*distortion_padding(camera, dist)) if distortion else camera
    rendered = []
    for index, spec in enumerate(specs):
        name = spec.kind if list(s.kind for s in specs).count(spec.kind) == 1 else f"{spec.kind}_{index}"
        rotations, translations = trajectory_object_to_camera(spec, np.random.default_rng([seed, index]))
        labels, poses, paths = [], [], []
        for k, (rot, r) in enumerate(zip(rotations, translations)):
            c2w_cv = object_to_camera_to_c2w(rot, r)
            rgb, _ = render_view(scene, c2w_cv, canvas, spp, seed=seed * 7919 + index * 100_003 + k)
            if distortion:
                rgb = distort_image(rgb, canvas, camera, dist)
            filename = f"img{k + 1:06d}.jpg"
            path = root / name / "synthetic" / "images" / filename
            write_image(path, rgb)
            labels.append({"filename": filename, "q_vbs2tango_true": rotmat_to_quat_wxyz(rot).tolist(),
                           "r_Vo2To_vbs_true": r.tolist()})
            poses.append(c2w_cv)
            paths.append(path)
            step()
        write_json_atomic(root / name / f"{name}.json", labels)
        write_json_atomic(root / name / "metadata.json",
                          {"pSim": {"cam_step": spec.frame_spacing_s, "num_images": spec.num_frames}})
        rendered.append(RenderedTrajectory(name, np.stack(poses), paths))
    return rendered
