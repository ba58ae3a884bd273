"""The lightbox-like domain: each lab-camera degradation against its documented value, the lab lighting, the
files and labels in SHIRT's layout, and the object mask found on its frames."""

import json
import subprocess
from dataclasses import replace
from pathlib import Path

import cv2
import mitsuba as mi
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from nerfinv_plugin.cli.bench import LIGHTBOX_RULES, LightboxBench
from nerfinv_plugin.cli.synth import Synth, TrajectoryOptions
from nerfinv_plugin.data.sequences import read_sequence
from nerfinv_plugin.geometry.frames import look_at_c2w_opencv, object_to_camera_to_c2w
from nerfinv_plugin.initialization.detect import find_object
from nerfinv_plugin.inversion.validation import uncovered
from nerfinv_plugin.synth.datasets import TrainingSetSpec, speedplus_like_camera
from nerfinv_plugin.synth.lab_scene import LAB_SUN_COLOUR, lab_scene, lab_sun_direction, render_linear
from nerfinv_plugin.synth.lightbox import LIGHTBOX, LabCamera, degrade, encode_jpeg, vignette_gain
from nerfinv_plugin.synth.lightbox_gap import mask_iou
from nerfinv_plugin.synth.render import linear_to_srgb
from nerfinv_plugin.synth.scenes import SUN_DIRECTION, build_scene
from nerfinv_plugin.synth.trajectories import TrajectorySpec, trajectory_object_to_camera

H, W = 150, 240
OFF = LabCamera(exposure=1.0, defocus_sigma_px=0.0, vignette_corner=1.0, bloom_strength=0.0, read_noise=0.0,
                shot_noise=0.0, gamma=1.0)
"""Every stage neutral: each test turns on the one it looks at."""


def _flat(value: float) -> np.ndarray:
    return np.full((H, W, 3), value, dtype=np.float32)


def test_neutral_camera_only_quantises() -> None:
    ramp = np.repeat(np.linspace(0.0, 1.0, W, dtype=np.float32)[None, :, None], 3, axis=2).repeat(H, axis=0)
    np.testing.assert_array_equal(degrade(ramp, np.random.default_rng(0), OFF), np.round(ramp * 255))


def test_exposure_and_gamma_darken_as_documented() -> None:
    x = np.linspace(0.0, 1.0, 11)
    out = degrade(np.repeat(x[None, :, None], 3, axis=2).astype(np.float32), np.random.default_rng(0),
                  replace(OFF, exposure=LIGHTBOX.exposure, gamma=LIGHTBOX.gamma))[0, :, 0]
    np.testing.assert_array_equal(out, np.round(255 * np.sqrt(0.8 * x)))
    # Against the training renders' sRGB encoding of the same light: mid-grey drops from 188 to 161.
    assert (out[5], round(float(linear_to_srgb(np.array(0.5)) * 255))) == (161, 188)


def test_vignette_falls_to_0_8_at_the_corners() -> None:
    out = degrade(_flat(1.0), np.random.default_rng(0), replace(OFF, vignette_corner=LIGHTBOX.vignette_corner))
    grey = out[..., 0].astype(float)
    centre = grey[H // 2 - 1:H // 2 + 1, W // 2 - 1:W // 2 + 1].mean()
    for corner in (grey[0, 0], grey[0, -1], grey[-1, 0], grey[-1, -1]):
        assert corner / centre == pytest.approx(0.8, abs=0.004)
    gain = vignette_gain(H, W, 0.8)
    assert gain.max() == pytest.approx(1.0, abs=1e-4) and gain.min() == pytest.approx(0.8, abs=1e-6)
    # Quadratic in the radius: the middle of the long edge is at 1 - 0.2 (119.5^2 / (119.5^2 + 74.5^2)).
    assert gain[H // 2, 0] == pytest.approx(1 - 0.2 * 119.5**2 / (119.5**2 + 74.5**2), abs=2e-3)


@pytest.mark.parametrize("level", [0.1, 0.25, 0.5])
def test_noise_has_the_documented_sigma(level: float) -> None:
    camera = replace(OFF, read_noise=LIGHTBOX.read_noise, shot_noise=LIGHTBOX.shot_noise)
    out = degrade(_flat(level), np.random.default_rng(1), camera).astype(float) / 255
    expected = np.sqrt(0.015**2 + 0.04**2 * level)  # 0.020, 0.025, 0.032: read and shot noise both count
    assert out.std() == pytest.approx(expected, rel=0.03), (out.std(), expected)
    assert out.mean() == pytest.approx(level, abs=0.002)


def test_defocus_blur_attenuates_a_fine_pattern_as_a_1px_gaussian() -> None:
    xs = np.arange(W)
    pattern = (0.5 + 0.3 * np.sin(2 * np.pi * xs / 4.0)).astype(np.float32)  # period 4 px
    image = np.repeat(np.repeat(pattern[None, :, None], H, axis=0), 3, axis=2)
    out = degrade(image, np.random.default_rng(0), replace(OFF, defocus_sigma_px=LIGHTBOX.defocus_sigma_px))
    row = out[H // 2, 8:-8, 0].astype(float) / 255 - 0.5
    amplitude = 2 * np.abs(np.mean(row * np.exp(-2j * np.pi * xs[8:-8] / 4.0)))
    # A Gaussian of sigma s scales frequency f by exp(-2 pi^2 s^2 f^2): 0.291 at s = 1, f = 1/4.
    assert amplitude / 0.3 == pytest.approx(np.exp(-2 * np.pi**2 / 16), abs=0.02)


def test_bloom_spreads_only_the_light_above_0_85() -> None:
    image = _flat(0.0)
    image[40:49, 60:69] = 1.85  # 1.0 above the threshold
    image[40:49, 160:169] = 0.80  # below it
    out = degrade(image, np.random.default_rng(0), replace(OFF, bloom_strength=LIGHTBOX.bloom_strength))
    excess = np.zeros((H, W))
    excess[40:49, 60:69] = 1.0
    halo = 0.4 * gaussian_filter(excess, sigma=2.0, mode="reflect", truncate=4.0)
    ring = np.zeros((H, W), bool)
    ring[36:53, 56:73] = True
    ring[40:49, 60:69] = False  # the square itself clips at 1
    np.testing.assert_allclose(out[ring, 0] / 255, halo[ring], atol=1 / 255)
    assert halo[ring].max() > 0.1  # a visible halo
    assert not out[36:53, 156:173][~np.pad(np.ones((9, 9), bool), 4)].any()  # nothing round the dim square


def test_jpeg_at_quality_75() -> None:
    rgb = degrade(_flat(0.3), np.random.default_rng(0))
    data = encode_jpeg(rgb)
    assert data[:2] == b"\xff\xd8"
    _, q75 = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 75])
    _, q95 = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert data == q75.tobytes() != q95.tobytes()


def test_degrade_refuses_a_non_rgb_image() -> None:
    with pytest.raises(ValueError, match="shape"):
        degrade(np.zeros((H, W), np.float32), np.random.default_rng(0))


def test_lab_light_is_turned_recoloured_and_has_no_earthshine() -> None:
    sun = SUN_DIRECTION / np.linalg.norm(SUN_DIRECTION)
    assert np.degrees(np.arccos(np.dot(lab_sun_direction(), sun))) == pytest.approx(40.0, abs=1e-9)
    training, lab = build_scene("tango", 0), lab_scene("tango", 0)
    assert "ambient" in training and "ambient" not in lab
    assert set(training) - {"ambient"} == set(lab)
    np.testing.assert_allclose(np.divide(lab["sun"]["irradiance"]["value"], training["sun"]["irradiance"]["value"]),
                               LAB_SUN_COLOUR)
    np.testing.assert_allclose(LAB_SUN_COLOUR, [1.0, 0.95, 0.85])
    # Seen from below the body (z = 0 face, lit by neither sun): only earthshine lights it in training.
    camera = speedplus_like_camera(60, 38)
    c2w = look_at_c2w_opencv(np.array([0.3, 0.2, -3.0]), np.array([0.0, 0.0, 0.16]), roll=0.0)
    lit, alpha = render_linear(mi.load_dict(training), c2w, camera, 8, 0)
    dark, _ = render_linear(mi.load_dict(lab), c2w, camera, 8, 0)
    body = alpha > 0.99
    assert body.sum() > 100
    assert lit[body].mean() > 0.01 and dark[body].mean() < 0.1 * lit[body].mean(), (lit[body].mean(),
                                                                                      dark[body].mean())


def _run(out: Path, lightbox: bool, frames: int = 2) -> None:
    none = TrainingSetSpec(train_views=0, val_views=0, test_views=0)
    Synth(out=out, seed=2, spp=4, training=none,
          trajectory=TrajectoryOptions(num_frames=frames, width=120, height=75, lightbox=lightbox)).main()


@pytest.fixture(scope="module")
def domains(tmp_path_factory) -> tuple[Path, Path, Path]:
    root = tmp_path_factory.mktemp("lightbox")
    for name, lightbox in (("a", True), ("b", True), ("plain", False)):
        _run(root / name, lightbox)
    return root / "a", root / "b", root / "plain"


def test_lightbox_images_in_shirt_layout_with_the_same_labels(domains) -> None:
    a, b, plain = domains
    for traj in ("roe1", "roe2"):
        labels = a / "shirt" / traj / f"{traj}.json"
        assert labels.read_bytes() == (plain / "shirt" / traj / f"{traj}.json").read_bytes()
        names = [label["filename"] for label in json.loads(labels.read_text())]
        images = sorted(p.name for p in (a / "shirt" / traj / "lightbox" / "images").iterdir())
        assert images == names == ["img000001.jpg", "img000002.jpg"]
        for name in names:
            lab = a / "shirt" / traj / "lightbox" / "images" / name
            assert lab.read_bytes()[:2] == b"\xff\xd8" and cv2.imread(str(lab)).shape == (75, 120, 3)
            assert lab.read_bytes() == (b / "shirt" / traj / "lightbox" / "images" / name).read_bytes()  # seeded
            synthetic = a / "shirt" / traj / "synthetic" / "images" / name
            assert synthetic.read_bytes() == (plain / "shirt" / traj / "synthetic" / "images" / name).read_bytes()
    assert (a / "shirt" / "camera.json").read_bytes() == (plain / "shirt" / "camera.json").read_bytes()
    assert not (plain / "shirt" / "roe1" / "lightbox").exists()


def test_lightbox_sequence_reads_with_the_synthetic_poses(domains) -> None:
    a, _, _ = domains
    synthetic, lightbox = (read_sequence(a / "shirt" / "roe2" / domain) for domain in ("synthetic", "lightbox"))
    assert lightbox.intrinsics == synthetic.intrinsics
    for s, lab in zip(synthetic.frames, lightbox.frames, strict=True):
        assert s.name == lab.name
        np.testing.assert_array_equal(s.c2w_true, lab.c2w_true)
        assert not np.array_equal(s.image, lab.image)


def _views(kind: str, frames: tuple[int, ...]) -> list[np.ndarray]:
    """Camera-to-body poses of frames of the seed 0 trajectory ``kind`` (the generator's own motion)."""
    spec = TrajectorySpec(kind=kind, num_frames=20)
    rng = np.random.default_rng([0, ("roe1", "roe2").index(kind)])
    rotations, translations = trajectory_object_to_camera(spec, rng)
    return [object_to_camera_to_c2w(rotations[k], translations[k]) for k in frames]


@pytest.fixture(scope="module")
def lab_renders() -> list[tuple[np.ndarray, np.ndarray]]:
    """Linear lab renders and alphas at 240 x 150: a well-lit roe1 frame and three roe2 frames that the lab
    lamp leaves mostly dark (where the detector before its smoothing step lost the object)."""
    scene = mi.load_dict(lab_scene("tango", 0))
    camera = speedplus_like_camera(W, H)
    views = _views("roe1", (0,)) + _views("roe2", (10, 12, 14))
    return [render_linear(scene, c2w, camera, 16, seed=k) for k, c2w in enumerate(views)]


def test_rendered_frame_differs_in_the_documented_ways(lab_renders) -> None:
    linear, alpha = lab_renders[0]
    frame = degrade(linear, np.random.default_rng(3)).astype(float)
    clean = np.round(linear_to_srgb(linear) * 255)
    inside = cv2.erode((alpha > 0.99).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    # Darker by the exposure and the gamma: the object's mean is what sqrt(0.8 x) predicts, within 8 % (noise
    # clipped at 0 lifts its dark pixels: +5 % measured; without the exposure it would be +12 % more), and
    # well below the sRGB encoding of the same light.
    predicted = 255 * np.sqrt(0.8 * vignette_gain(H, W, 0.8)[..., None] * np.clip(linear, 0, 1))
    assert frame[inside].mean() == pytest.approx(predicted[inside].mean(), rel=0.08)
    assert frame[inside].mean() < 0.9 * clean[inside].mean()
    # The background: clipped read noise under gamma 2. Half the values are 0, and the median of the others
    # is 0.674 sigma once decoded.
    background = cv2.dilate((alpha > 0).astype(np.uint8), np.ones((15, 15), np.uint8)) == 0
    decoded = (frame[background] / 255) ** 2
    assert (decoded == 0).mean() == pytest.approx(0.5, abs=0.02)
    assert np.median(decoded[decoded > 0]) / 0.6745 == pytest.approx(LIGHTBOX.read_noise, rel=0.08)
    # Blur: less high-frequency energy (Laplacian) on the object than the clean render has, noise aside.
    quiet = degrade(linear, np.random.default_rng(3), replace(LIGHTBOX, read_noise=0.0, shot_noise=0.0))
    sharp = np.round(255 * np.sqrt(0.8 * vignette_gain(H, W, 0.8)[..., None] * np.clip(linear, 0, 1)))
    energy = [np.mean(cv2.Laplacian(image.astype(np.float32), cv2.CV_32F)[inside] ** 2) for image in (quiet, sharp)]
    assert energy[0] < 0.5 * energy[1], energy


def test_find_object_survives_the_lab_camera(lab_renders) -> None:
    """Measured on 40 frames (seeds 0 and 1, every other frame of roe1 and roe2, 240 x 150, 16 spp), IoU with
    the alpha: the mask found on a lightbox frame (after JPEG) scored at most 0.066 below the mask found on
    the clean render of the same lab light (on well-lit frames, where the defocus and bloom widen the
    outline: 0.90 against 0.96), and above it on 20 of the 40; the detector without its smoothing step lost
    the object on two of the roe2 frames here and scored 0.12 below on the third."""
    for k, (linear, alpha) in enumerate(lab_renders):
        jpeg = np.frombuffer(encode_jpeg(degrade(linear, np.random.default_rng([0, k]))), np.uint8)
        frame = cv2.cvtColor(cv2.imdecode(jpeg, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        clean = find_object(np.round(linear_to_srgb(linear) * 255).astype(np.uint8))
        found = find_object(frame)
        assert found is not None, f"view {k}: no object found"
        silhouette = alpha > 0.5
        got, ref = mask_iou(found.mask, silhouette, alpha.shape), mask_iou(clean.mask, silhouette, alpha.shape)
        assert got >= ref - 0.08, (k, got, ref)
        if k == 0:
            assert got >= 0.85, got


def test_gap_command_checks_its_options(tmp_path: Path) -> None:
    assert uncovered(LightboxBench, LIGHTBOX_RULES) == []
    done = subprocess.run(["ns-invert-bench", "lightbox", "--out", str(tmp_path / "gap"), "--num-frames", "0"],
                          capture_output=True, text=True)
    assert done.returncode == 2 and "--num-frames must be" in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "gap").exists()
