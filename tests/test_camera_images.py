"""nerfacto-tiny learns from what users have: RGB images without alpha on a black background, trained
through nerfstudio-data with its defaults, scored on the same held-out views as the Blender-path model."""

import json

import cv2

from nerfinv_plugin.model.evaluate import score_split
from nerfinv_plugin.model.loading import load_model


def test_camera_images_are_rgb_without_alpha_with_the_same_poses(toy_rgb_run):
    rgb = toy_rgb_run[0].parents[4] / "rgb"
    meta = json.loads((rgb / "transforms.json").read_text())
    original = json.loads((toy_rgb_run[1] / "transforms.json").read_text())
    assert [f["transform_matrix"] for f in meta["frames"]] == [f["transform_matrix"] for f in original["frames"]]
    assert len(meta["test_filenames"]) == len(original["test_filenames"]) == 6
    image = cv2.imread(str(rgb / meta["frames"][0]["file_path"]), cv2.IMREAD_UNCHANGED)
    assert image.ndim == 3 and image.shape[2] == 3


def test_a_model_trained_on_camera_images_learns_as_the_blender_path_does(toy_rgb_run, toy_run):
    rgb_model = score_split(load_model(toy_rgb_run[0], device="cpu"), toy_rgb_run[1], "blender")
    blender_model = score_split(load_model(toy_run[0], device="cpu"), toy_run[1], "blender")
    assert rgb_model.black_psnr == blender_model.black_psnr  # the same held-out views and images
    # Before issue 12: 0 dB, an all-black render, and a gap of about 10 dB to the Blender path. Four trainings
    # of this fixture with the same settings gave margins of 8.16, 6.94, 7.38 and 5.46 dB and gaps of 1.9,
    # 3.5, 2.6 and 4.6 dB (training is not bit-reproducible: thread counts, data loader workers and the load
    # on the machine change it), so the test guards against a model that learns nothing, with room for that
    # spread; the targets (8 dB above all-black, within 1 dB of the Blender path) are measured in
    # docs/benchmarks.md, not here. Since densities are measured per contraction unit (2026-12-04; before, the
    # last training of the old code gave a margin of 7.00 dB and a gap of 3.9 dB): margin 9.42 dB, gap 0.58 dB,
    # so the bounds now catch a return of the unit-cube gap while leaving room for the spread. With the opacity
    # loss for RGB images (2026-12-07): margin 9.49 dB, gap 0.84 dB.
    assert rgb_model.margin_db > 7.0, rgb_model
    assert rgb_model.mean_psnr > blender_model.mean_psnr - 2.5, (rgb_model.mean_psnr, blender_model.mean_psnr)
