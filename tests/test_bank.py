"""Pose from nothing: translation from a box against an analytic projection, the icosphere, the bank's
in-plane angles against a rolled camera, bank recall on the fixture's held-out views, the object's extent,
and the caches of the bank and of its entries."""

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nerfinv_plugin.data.images import read_rgb_over_black
from nerfinv_plugin.geometry.frames import OPENCV_TO_OPENGL
from nerfinv_plugin.geometry.se3 import geodesic_deg
from nerfinv_plugin.initialization import bank as bank_module
from nerfinv_plugin.initialization import extent
from nerfinv_plugin.initialization.bank import (
    BankConfig,
    bank_entries,
    bank_intrinsics,
    cached_bank,
    cached_entries,
    entries_file,
    hypotheses,
    icosphere,
    render_bank,
)
from nerfinv_plugin.initialization.box_pose import BankView, pose_from_box, rotation_between
from nerfinv_plugin.initialization.detect import find_object
from nerfinv_plugin.initialization.extent import object_radius
from nerfinv_plugin.inversion.session import bound_rays
from nerfinv_plugin.inversion.settings import RenderConfig
from nerfinv_plugin.model.loading import load_model
from nerfinv_plugin.model.render import AS_TRAINED, Intrinsics, render_image
from nerfinv_plugin.synth.scenes import SCENE_CENTRES

TOY_CENTRE = np.asarray(SCENE_CENTRES["toy"], dtype=np.float64)


def _project(points: np.ndarray, w2c: np.ndarray, t: np.ndarray, f: float, cx: float, cy: float) -> np.ndarray:
    cam = points @ w2c.T + t
    return np.stack([f * cam[:, 0] / cam[:, 2] + cx, f * cam[:, 1] / cam[:, 2] + cy], 1)


def _box(uv: np.ndarray) -> tuple[tuple[float, float], float]:
    lo, hi = uv.min(0), uv.max(0)
    return (float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2)), float(max(hi - lo))


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.9, -0.4), (-1.2, 0.8)])
def test_translation_from_a_box_matches_an_analytic_projection(offset):
    rng = np.random.default_rng(1)
    points = rng.uniform(-1, 1, size=(400, 3)) * np.array([0.6, 0.4, 0.25])  # an asymmetric box of points
    points[:50] += np.array([0.5, 0.1, 0.0])  # and an arm, so the box centre is off the object's origin
    w2c = rotation_between(np.array([0.0, 0.0, 1.0]), rng.normal(size=3))  # any attitude
    # The observed camera: object 7 m away, off the axis by ``offset`` metres (x, y).
    t_true = np.array([offset[0], offset[1], 7.0])
    f, cx, cy = 600.0, 320.0, 240.0
    rotation_true = rotation_between(np.array([0.0, 0.0, 1.0]), t_true) @ w2c
    box_centre, box_size = _box(_project(points, rotation_true, t_true, f, cx, cy))
    # The bank's centred view of the same attitude: 6 m away (at 3 m the box grows 5% faster than 1 / range
    # with this object's depth: perspective, which the tracker refines), another focal length.
    bank_f, bank_d, bank_c = 150.0, 6.0, 32.0
    bank_centre, bank_size = _box(_project(points, w2c, np.array([0.0, 0.0, bank_d]), bank_f, bank_c, bank_c))
    view = BankView(w2c, bank_d, bank_f, (bank_centre[0] - bank_c, bank_centre[1] - bank_c), bank_size)
    centre = np.array([0.3, -0.2, 0.1])  # the object's origin in the world
    c2w = pose_from_box(view, box_centre, box_size, f, f, cx, cy, centre)
    rotation = c2w[:3, :3].T
    t = rotation @ (centre - c2w[:3, 3])  # the object's origin in the recovered camera frame
    assert np.linalg.norm(t - t_true) < 0.02 * np.linalg.norm(t_true), (t, t_true)
    angle = np.degrees(np.arccos(np.clip((np.trace(rotation.T @ rotation_true) - 1) / 2, -1, 1)))
    assert angle < 0.5, angle
    # The recovered pose puts the object where it was seen.
    reprojected = _project(points, rotation, t, f, cx, cy)
    assert abs(_box(reprojected)[1] - box_size) < 0.03 * box_size


def test_icosphere_has_the_expected_viewpoints():
    for n, count in [(0, 12), (1, 42), (2, 162), (3, 642)]:
        points = icosphere(n)
        assert points.shape == (count, 3) and np.allclose(np.linalg.norm(points, axis=1), 1.0)
        assert BankConfig(subdivisions=n).views == count
    points = icosphere(3)
    nearest = np.sort(np.degrees(np.arccos(np.clip(points @ points.T, -1, 1))), axis=1)[:, 1]
    assert nearest.max() < 10.0 and nearest.min() > 5.0  # about 8 degrees apart, evenly


RADIUS_M = 0.8
"""A sphere about the toy's centre that holds it (its farthest point is 0.73 m away)."""


@pytest.fixture(scope="module")
def toy_model(toy_run):
    """The fixture model as loaded."""
    return load_model(toy_run[0], device="cpu")


@pytest.fixture(scope="module")
def bounded(toy_model):
    """How ns-invert renders the fixture model (rays bounded to the object, (16, 8) / 16 samples)."""
    centre = torch.as_tensor(toy_model.point_to_model(TOY_CENTRE), dtype=torch.float32)
    return bound_rays(toy_model, centre, RenderConfig(target_radius_m=RADIUS_M))[0]


def test_object_radius_from_the_density_holds_the_toy_and_is_not_much_larger(toy_model):
    centre = torch.as_tensor(toy_model.point_to_model(TOY_CENTRE), dtype=torch.float32)
    radius = object_radius(toy_model, centre) / toy_model.dataparser_scale
    # The toy object (synth/scenes.py): its farthest point, the tower's top corner, is 0.73 m from the centre.
    assert 0.72 < radius < 1.0, radius


def test_object_radius_is_not_inflated_by_a_fog_of_specks_touching_the_object(toy_model, monkeypatch):
    """A model trained on RGB images over black can fill the space about the object with specks of dark fog
    just above the occupancy threshold that touch one another and the object (measured: 2.57 m for the
    0.73 m toy). Here 45% of the cells within twice the object's radius get a speck 1.3 times the
    threshold: at the threshold alone they join the object, and the radius must still stay the object's."""
    centre = torch.as_tensor(toy_model.point_to_model(TOY_CENTRE), dtype=torch.float32)
    clean = object_radius(toy_model, centre)
    field = extent.density_field(toy_model)
    scene = float(toy_model.model.scene_box.aabb.abs().max())
    threshold = extent.base_density(scene)
    lattice = 0.013  # model units: finer than either pass's cells, so every cell samples its own specks

    def foggy(points: torch.Tensor) -> torch.Tensor:
        cells = torch.floor(points / lattice).long()
        hashed = (cells[..., 0] * 73856093) ^ (cells[..., 1] * 19349663) ^ (cells[..., 2] * 83492791)
        speck = (hashed.remainder(1000) < 450) & ((points - centre).norm(dim=-1) < 2.0 * clean)
        return field.density_fn(points) + (1.3 * threshold * speck).reshape(*points.shape[:-1], 1)

    monkeypatch.setattr(extent, "density_field", lambda loaded: SimpleNamespace(density_fn=foggy))
    at_threshold = extent._radius_at(lambda half: extent.DensityGrid.measure(toy_model, centre, half), scene, threshold)
    assert at_threshold > 1.4 * clean / extent.MARGIN, (at_threshold, clean)  # the fog joined the object
    assert abs(object_radius(toy_model, centre) - clean) < 0.1 * clean, clean


def test_a_dense_speck_by_the_centre_of_a_hollow_object_is_not_taken_for_it(toy_model, monkeypatch):
    """The occupied cell nearest the centre may be a speck apart from the object (measured: a user's-path
    spacecraft whose fine pass at 8x the threshold took such a one-cell speck for the object, 0.015 of its
    0.175 model units, and whose view bank then saw nothing). Here the toy is emptied within half its radius
    and a speck far denser than every threshold, a tenth of its radius, put at the centre: the radius must stay
    the toy's."""
    centre = torch.as_tensor(toy_model.point_to_model(TOY_CENTRE), dtype=torch.float32)
    clean = object_radius(toy_model, centre)
    field = extent.density_field(toy_model)
    dense = 100.0 * extent.base_density(float(toy_model.model.scene_box.aabb.abs().max()))

    def hollow_with_speck(points: torch.Tensor) -> torch.Tensor:
        distance = (points - centre).norm(dim=-1)
        inside = (distance < 0.5 * clean / extent.MARGIN).reshape(*points.shape[:-1], 1)
        speck = (distance < 0.1 * clean).reshape(*points.shape[:-1], 1)
        return torch.where(inside, dense * speck, field.density_fn(points))

    monkeypatch.setattr(extent, "density_field", lambda loaded: SimpleNamespace(density_fn=hollow_with_speck))
    assert abs(object_radius(toy_model, centre) - clean) < 0.1 * clean, clean


def test_a_thin_diagonal_boom_counts_as_part_of_the_object(toy_model, monkeypatch):
    """A boom thinner than a grid cell running diagonally through the grid occupies a chain of cells that
    touch only at their corners (measured: a fine pass that joined cells by their faces alone cut a user's-path
    spacecraft to 0.17 m of its 0.8 m). A boom from the centre out to 1.5 times the clean radius, along the
    grid's diagonal, must widen the radius to hold it."""
    centre = torch.as_tensor(toy_model.point_to_model(TOY_CENTRE), dtype=torch.float32)
    clean = object_radius(toy_model, centre)
    field = extent.density_field(toy_model)
    dense = 20.0 * extent.base_density(float(toy_model.model.scene_box.aabb.abs().max()))
    axis = torch.ones(3) / np.sqrt(3.0)

    def with_boom(points: torch.Tensor) -> torch.Tensor:
        offset = points - centre
        along = offset @ axis
        off_axis = (offset - along[..., None] * axis).norm(dim=-1)
        boom = (off_axis < 1e-4) & (along > 0) & (along < 1.5 * clean)
        return field.density_fn(points) + (dense * boom).reshape(*points.shape[:-1], 1)

    monkeypatch.setattr(extent, "density_field", lambda loaded: SimpleNamespace(density_fn=with_boom))
    assert object_radius(toy_model, centre) > 1.4 * clean, clean


def test_an_in_plane_angle_of_the_bank_is_a_rolled_camera(toy_model, bounded):
    """Entry 1 of view 0 (in-plane angle 90 degrees) claims a rolled camera: rendering that camera gives the
    view's image turned a quarter clockwise (x right, y down: right goes to down), which np.rot90 does
    exactly; the other sense of rotation must not match."""
    config = BankConfig(subdivisions=0, in_plane=4, render_px=48)
    radius = RADIUS_M * toy_model.dataparser_scale
    centre = toy_model.point_to_model(TOY_CENTRE)
    bank = render_bank(toy_model, bounded, centre, radius, config)
    entries = bank_entries(bank, config)
    assert len(entries.views) == config.views * config.in_plane
    intrinsics = bank_intrinsics(config)
    c2w_cv = np.eye(4)
    c2w_cv[:3, :3] = entries.views[1].w2c_rotation.T
    c2w_cv[:3, 3] = bank.c2w[0][:3, 3]
    rolled = render_image(toy_model, c2w_cv @ OPENCV_TO_OPENGL, intrinsics, bounded)
    view = bank.rgb[0].astype(np.float64) / 255.0
    clockwise, anticlockwise = np.rot90(view, k=-1), np.rot90(view, k=1)
    assert np.abs(rolled - clockwise).mean() < 0.25 * np.abs(rolled - anticlockwise).mean()
    assert np.abs(rolled - clockwise).mean() < 0.01
    # The entry's box is where the detector finds the object in the rolled render.
    found = find_object((rolled * 255 + 0.5).astype(np.uint8))
    box = entries.views[1]
    assert abs(found.centre[0] - (24 + box.box_offset[0])) < 1.0
    assert abs(found.centre[1] - (24 + box.box_offset[1])) < 1.0
    assert abs(found.size - box.box_size) < 1.5


def test_the_bank_recalls_the_held_out_views(toy_model, bounded, toy_run):
    """Every held-out view of the fixture has a hypothesis within 15 degrees among its first 20."""
    config = BankConfig(subdivisions=2)
    radius = RADIUS_M * toy_model.dataparser_scale
    centre = toy_model.point_to_model(TOY_CENTRE)
    entries = bank_entries(render_bank(toy_model, bounded, centre, radius, config), config)
    data = toy_run[1]
    meta = json.loads((data / "transforms_test.json").read_text())
    best = []
    for frame in meta["frames"]:
        path = data / (frame["file_path"].removeprefix("./") + ".png")
        image = (read_rgb_over_black(path) * 255 + 0.5).astype(np.uint8)
        height, width = image.shape[:2]
        focal = 0.5 * width / np.tan(0.5 * meta["camera_angle_x"])
        intrinsics = Intrinsics(focal, focal, width / 2, height / 2, width, height)
        truth = toy_model.dataset_to_model(np.asarray(frame["transform_matrix"]))
        detection = find_object(image)
        assert detection is not None
        found = hypotheses(entries, image, detection, intrinsics, centre, 20, config)
        errors = geodesic_deg(torch.as_tensor(np.array([h.c2w[:3, :3] for h in found])),
                              torch.as_tensor(truth[:3, :3]).expand(len(found), 3, 3)).numpy()
        best.append(errors.min())
        true_range = np.linalg.norm(truth[:3, 3] - centre)
        assert abs(np.linalg.norm(found[0].c2w[:3, 3] - centre) - true_range) < 0.15 * true_range  # from the box
    assert max(best) < 15.0, best


def test_the_bank_cache_is_reused_and_rebuilt_when_the_checkpoint_changes(toy_run, tmp_path, monkeypatch):
    monkeypatch.setenv("NERFINV_CACHE", str(tmp_path / "cache"))
    run = tmp_path / "run"
    shutil.copytree(toy_run[0].parent, run)
    config = BankConfig(subdivisions=0, render_px=16)
    loaded = load_model(run / "config.yml", device="cpu")
    centre = loaded.point_to_model(TOY_CENTRE)
    first, path, built = cached_bank(loaded, AS_TRAINED, centre, 0.8, config)
    assert built and path.is_file()
    again, path_again, built_again = cached_bank(loaded, AS_TRAINED, centre, 0.8, config)
    assert not built_again and path_again == path and np.array_equal(again.rgb, first.rgb)
    # A retrained model: same file name, other weights.
    checkpoint = next((run / "nerfstudio_models").glob("*.ckpt"))
    saved = torch.load(checkpoint, weights_only=False)
    key = "_model.field.mlp_base.model.0.hash_table"
    saved["pipeline"][key] = saved["pipeline"][key] * 0.5
    torch.save(saved, checkpoint)
    changed = load_model(run / "config.yml", device="cpu")
    _, path_changed, built_changed = cached_bank(changed, AS_TRAINED, centre, 0.8, config)
    assert built_changed and path_changed != path
    # Other bank settings are another bank too.
    _, path_other, built_other = cached_bank(changed, AS_TRAINED, centre, 0.8, BankConfig(subdivisions=0, render_px=20))
    assert built_other and path_other != path_changed
    assert Path(path_other).parent == tmp_path / "cache" / "banks"


def test_cached_entries_round_trip_exactly_and_follow_the_bank_settings_and_the_detector(toy_model, bounded,
                                                                                          tmp_path, monkeypatch):
    """The entries read back are the computed ones to the bit; other entry settings, or another detector's
    source, are another file (computed again, never stale)."""
    config = BankConfig(subdivisions=0, in_plane=6, render_px=24, crop_px=16)
    centre = toy_model.point_to_model(TOY_CENTRE)
    bank = render_bank(toy_model, bounded, centre, RADIUS_M * toy_model.dataparser_scale, config)
    bank_path = tmp_path / "bank-x.npz"
    computed = cached_entries(bank, bank_path, config)
    path = entries_file(bank_path, config)
    assert path.is_file() and len(computed.views) >= 6
    monkeypatch.setattr(bank_module, "bank_entries", lambda *args: pytest.fail("entries computed again"))
    read = cached_entries(bank, bank_path, config)
    for name in ("masks", "greys", "quaternions"):
        assert getattr(read, name).dtype == getattr(computed, name).dtype
        assert np.array_equal(getattr(read, name), getattr(computed, name))
    assert all(
        np.array_equal(a.w2c_rotation, b.w2c_rotation) and (a.range, a.focal, a.box_offset, a.box_size)
        == (b.range, b.focal, b.box_offset, b.box_size) for a, b in zip(read.views, computed.views, strict=True))
    assert entries_file(bank_path, BankConfig(subdivisions=0, in_plane=12, render_px=24, crop_px=16)) != path
    detector = tmp_path / "detect.py"
    detector.write_text(Path(find_object.__code__.co_filename).read_text() + "\n# changed\n")
    monkeypatch.setattr(find_object, "__code__", find_object.__code__.replace(co_filename=str(detector)))
    assert entries_file(bank_path, config) != path
