"""Synthetic data: SHIRT files that give back the rendering poses, keypoints on the silhouette,
Blender/nerfstudio transforms, lens distortion, determinism and the CLI."""

import json
import subprocess

import cv2
import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nerfinv_plugin.geometry.frames import look_at_c2w_opencv
from nerfinv_plugin.synth.datasets import (
    SPEEDPLUS_DIST_COEFFS,
    TrainingSetSpec,
    speedplus_like_camera,
    write_shirt_trajectories,
    write_training_set,
)
from nerfinv_plugin.synth.render import distort_image, distortion_padding, render_view
from nerfinv_plugin.synth.scenes import SATELLITE_SPAN_M, SCENE_CENTRES, TANGO_KEYPOINTS, build_scene
from nerfinv_plugin.synth.trajectories import TrajectorySpec

SPECS = [TrajectorySpec(kind="roe1", num_frames=4), TrajectorySpec(kind="roe2", num_frames=4)]


def _noop() -> None:
    pass


@pytest.fixture(scope="module")
def shirt(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    camera = speedplus_like_camera(240, 150)
    rendered = write_shirt_trajectories(out, "tango", SPECS, camera, False, seed=3, spp=8, step=_noop)
    return out, camera, rendered


def _label_c2w_scipy(label: dict) -> np.ndarray:
    """Independent reading of a SHIRT label: scipy wants scalar-last quaternions."""
    w, x, y, z = label["q_vbs2tango_true"]
    rot = Rotation.from_quat([x, y, z, w]).as_matrix()
    r = np.asarray(label["r_Vo2To_vbs_true"])
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot.T, -rot.T @ r
    return c2w


def test_shirt_layout_and_keys(shirt):
    out, camera, rendered = shirt
    root = out / "shirt"
    cam = json.loads((root / "camera.json").read_text())
    assert set(cam) == {"Nu", "Nv", "ppx", "ppy", "fx", "fy", "ccx", "ccy", "cameraMatrix", "distCoeffs"}
    assert (cam["Nu"], cam["Nv"]) == (240, 150)
    assert cam["cameraMatrix"][0][0] == pytest.approx(cam["fx"] / cam["ppx"])
    for traj in rendered:
        labels = json.loads((root / traj.name / f"{traj.name}.json").read_text())
        assert [lab["filename"] for lab in labels] == [f"img{k:06d}.jpg" for k in range(1, 5)]
        for lab in labels:
            assert set(lab) == {"filename", "q_vbs2tango_true", "r_Vo2To_vbs_true"}
            image = cv2.imread(str(root / traj.name / "synthetic" / "images" / lab["filename"]))
            assert image.shape == (150, 240, 3)


def test_shirt_labels_give_back_the_render_poses(shirt):
    out, _, rendered = shirt
    for traj in rendered:
        labels = json.loads((out / "shirt" / traj.name / f"{traj.name}.json").read_text())
        for label, c2w in zip(labels, traj.c2w_opencv):
            np.testing.assert_allclose(_label_c2w_scipy(label), c2w, atol=1e-12)
            assert label["q_vbs2tango_true"][0] >= 0  # scalar first, canonical sign


def test_roe1_holds_range_and_spins_about_one_axis(shirt):
    out, _, rendered = shirt
    labels = json.loads((out / "shirt" / "roe1" / "roe1.json").read_text())
    ranges = [np.linalg.norm(lab["r_Vo2To_vbs_true"]) for lab in labels]
    np.testing.assert_allclose(ranges, 5.0, atol=1e-12)
    rots = [Rotation.from_matrix(_label_c2w_scipy(lab)[:3, :3].T) for lab in labels]
    steps = [(rots[k].inv() * rots[k + 1]) for k in range(len(rots) - 1)]
    # Body-frame increments: the same 4 degrees about body z every frame (0.8 deg/s x 5 s).
    for step in steps:
        np.testing.assert_allclose(step.as_rotvec(), [0, 0, np.radians(4.0)], atol=1e-9)
    roe2 = json.loads((out / "shirt" / "roe2" / "roe2.json").read_text())
    ranges2 = [np.linalg.norm(lab["r_Vo2To_vbs_true"]) for lab in roe2]
    assert ranges2[0] > ranges2[-1] and np.all(np.diff(ranges2) < 0)  # approaching


def _on_silhouette(points: np.ndarray, mask: np.ndarray, tolerance_px: int = 2) -> np.ndarray:
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((2 * tolerance_px + 1,) * 2, np.uint8))
    inside = []
    for u, v in np.round(points).astype(int):
        inside.append(0 <= v < mask.shape[0] and 0 <= u < mask.shape[1] and bool(grown[v, u]))
    return np.array(inside)


def test_keypoints_projected_with_label_and_k_fall_on_the_silhouette(shirt):
    out, camera, rendered = shirt
    cam = json.loads((out / "shirt" / "camera.json").read_text())
    scene = mi.load_dict(build_scene("tango", 3))
    for traj in rendered:
        labels = json.loads((out / "shirt" / traj.name / f"{traj.name}.json").read_text())
        for label, c2w in zip(labels, traj.c2w_opencv):
            _, alpha = render_view(scene, c2w, camera, spp=8, seed=0)
            w, x, y, z = label["q_vbs2tango_true"]
            rvec = Rotation.from_quat([x, y, z, w]).as_rotvec()
            pts, _ = cv2.projectPoints(TANGO_KEYPOINTS, rvec, np.asarray(label["r_Vo2To_vbs_true"]),
                                       np.asarray(cam["cameraMatrix"]), np.asarray(cam["distCoeffs"]))
            on = _on_silhouette(pts[:, 0], alpha > 0.05)
            assert on.all(), f"{traj.name} {label['filename']}: keypoints {np.flatnonzero(~on) + 1} off the object"
            # The same points with the quaternion read scalar-last (a common mistake) must miss.
            wrong = Rotation.from_quat([w, x, y, z]).as_rotvec()
            pts_wrong, _ = cv2.projectPoints(TANGO_KEYPOINTS, wrong, np.asarray(label["r_Vo2To_vbs_true"]),
                                             np.asarray(cam["cameraMatrix"]), np.zeros(5))
            assert not _on_silhouette(pts_wrong[:, 0], alpha > 0.05, 0).all()


def test_distort_image_is_undone_by_opencv_undistort():
    camera = speedplus_like_camera(240, 150)
    dist = np.array([-0.4, 0.2, 0.002, -0.001, 0.0])  # stronger than SPEED+'s, so shifts reach pixels
    canvas = camera.padded(*distortion_padding(camera, dist))
    ys, xs = np.mgrid[0:canvas.height, 0:canvas.width]
    pattern = lambda x, y: 127 + 100 * np.sin(x / 6.0) * np.cos(y / 5.0)  # noqa: E731
    ideal_canvas = pattern(xs, ys).astype(np.float32)
    pad_x, pad_y = canvas.cx - camera.cx, canvas.cy - camera.cy
    ideal = ideal_canvas[int(pad_y):int(pad_y) + camera.height, int(pad_x):int(pad_x) + camera.width]
    distorted = distort_image(ideal_canvas, canvas, camera, dist)
    undone = cv2.undistort(distorted, camera.matrix, dist)
    core = (slice(10, -10), slice(10, -10))
    undone_err = np.abs(undone[core] - ideal[core]).mean()
    raw_err = np.abs(distorted[core] - ideal[core]).mean()
    assert undone_err < 1.0 and raw_err > 10 * undone_err, (undone_err, raw_err)


def test_distortion_option_writes_its_coefficients_and_warps_images(tmp_path):
    camera = speedplus_like_camera(240, 150)
    spec = [TrajectorySpec(kind="roe1", num_frames=1, range_m=2.5)]
    ideal = write_shirt_trajectories(tmp_path / "a", "toy", spec, camera, False, seed=1, spp=4, step=_noop)
    warped = write_shirt_trajectories(tmp_path / "b", "toy", spec, camera, True, seed=1, spp=4, step=_noop)
    np.testing.assert_allclose(json.loads((tmp_path / "b" / "shirt" / "camera.json").read_text())["distCoeffs"],
                               SPEEDPLUS_DIST_COEFFS)
    assert json.loads((tmp_path / "a" / "shirt" / "camera.json").read_text())["distCoeffs"] == [0.0] * 5
    a, b = (cv2.imread(str(t[0].image_paths[0])) for t in (ideal, warped))
    assert a.shape == b.shape and np.abs(a.astype(int) - b.astype(int)).mean() > 1.0


def test_training_set_formats_and_determinism(tmp_path):
    spec = TrainingSetSpec(train_views=3, val_views=1, test_views=1, width=40, height=25)
    for name in ("a", "b"):
        write_training_set(tmp_path / name, "toy", spec, seed=5, spp=4, step=_noop)
    write_training_set(tmp_path / "c", "toy", spec, seed=6, spp=4, step=_noop)
    blender = json.loads((tmp_path / "a" / "transforms_train.json").read_text())
    assert len(blender["frames"]) == 3
    focal = 0.5 * 40 / np.tan(0.5 * blender["camera_angle_x"])
    ns = json.loads((tmp_path / "a" / "transforms.json").read_text())
    assert ns["fl_x"] == pytest.approx(focal) and (ns["w"], ns["h"], ns["cx"]) == (40, 25, 20.0)
    assert len(ns["train_filenames"]) == 3 and len(ns["test_filenames"]) == 1
    for frame in blender["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        # OpenGL axes: the camera looks along -z, towards the object near the origin.
        assert np.dot(-c2w[:3, 2], -c2w[:3, 3]) / np.linalg.norm(c2w[:3, 3]) > 0.99
        assert (tmp_path / "a" / (frame["file_path"][2:] + ".png")).is_file()
    same = [(tmp_path / n / "train" / "r_000.png").read_bytes() for n in ("a", "b", "c")]
    assert same[0] == same[1] and same[0] != same[2]


def test_satellite_wings_span_their_length_and_are_thinner_than_a_pixel_edge_on():
    """The thin-parts satellite at the nearest training range (4.5 m) on the training camera: with the wings
    across the image's short side they span 1.7 m (the analytic projection, within 2 pixels) and stay inside
    the frame; seen edge-on (camera in the wings' plane) they cover under a pixel's height."""
    camera = speedplus_like_camera(120, 75)
    scene = mi.load_dict(build_scene("satellite", 0))
    centre = SCENE_CENTRES["satellite"]
    across = look_at_c2w_opencv(centre + [0.0, 0.0, 4.5], centre, up=np.array([0.0, 1.0, 0.0]))
    _, alpha = render_view(scene, across, camera, spp=16, seed=0)
    rows = np.flatnonzero((alpha > 0.3).any(1))
    span_px = camera.focal * SATELLITE_SPAN_M / (4.5 + 0.1 - 0.055)   # the wings' near face is at z = 0.055
    assert rows[0] > 0 and rows[-1] < 74 and abs(rows[-1] + 1 - rows[0] - span_px) < 2, (rows[[0, -1]], span_px)

    edge_on = look_at_c2w_opencv(centre + [4.5, 0.0, -0.05], centre + [0.0, 0.0, -0.05])
    _, alpha = render_view(scene, edge_on, camera, spp=64, seed=0)
    columns = np.abs(np.arange(120) - camera.cx) * 4.5 / camera.focal > 0.5      # beyond the bus, yokes and whip
    wing_rows = alpha[:, columns]
    assert wing_rows.max() > 0.05 and wing_rows.sum(0).max() < 1.0, wing_rows.sum(0).max()


def test_cli_help_documents_every_option():
    text = subprocess.run(["ns-invert-synth", "--help"], capture_output=True, text=True, check=True).stdout
    for option in ("--out", "--scene", "--seed", "--spp", "--training.train-views", "--training.range-m",
                   "--trajectory.kinds", "--trajectory.frame-spacing-s", "--trajectory.range-m",
                   "--trajectory.spin-rate-deg-s", "--trajectory.width", "--trajectory.distortion",
                   "--trajectory.lightbox"):
        assert option in text, option
    assert "SHIRT" in text
