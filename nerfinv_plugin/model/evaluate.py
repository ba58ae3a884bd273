"""Image quality of a trained model on the held-out views of the data it was trained on.

A run comes from one of three dataparsers, and each keeps its held-out views in its own layout: Blender
(``transforms_<split>.json``), nerfstudio (``transforms.json``, split by file lists or by nerfstudio's
fraction rule) and SPEED+ (``camera.json`` and label files, split by ``speedplus-data``). Each reader
reduces its layout to the same views (image, dataset-frame pose, pinhole intrinsics, lens distortion), so
one code path scores them all and two layouts that hold the same views score the same.

Every view is also scored as an all-black image. On a dark-background scene a model that renders nothing
still gets that score, so only the margin above it shows that the model learned the object.
"""

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.data.utils.dataparsers_utils import (
    get_train_eval_split_all,
    get_train_eval_split_filename,
    get_train_eval_split_fraction,
    get_train_eval_split_interval,
)

from nerfinv_plugin.data.camera_and_labels import label_c2w_opengl
from nerfinv_plugin.data.images import ImageError, image_size, read_rgb_over_black
from nerfinv_plugin.data.speedplus import (
    SpeedPlusDataParserConfig,
    evenly_spaced,
    image_paths,
    read_camera,
    select_labels,
)
from nerfinv_plugin.model.loaded import LoadedModel
from nerfinv_plugin.model.render import Intrinsics, render_image

DataFormat = Literal["blender", "nerfstudio", "speedplus"]
FormatChoice = Literal["auto", "blender", "nerfstudio", "speedplus"]
Split = Literal["train", "val", "test"]

BLENDER_SPLITS = ("train", "val", "test")
SPEEDPLUS_DOMAINS = ("synthetic", "lightbox", "sunlamp")
PINHOLE_CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""nerfstudio camera models that are a pinhole with at most OpenCV radial-tangential distortion."""
LEGACY_COLMAP_TRANSFORM = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]
"""The ``applied_transform`` nerfstudio-data assumes for COLMAP output written before the field existed."""


class DataFormatError(Exception):
    """A data folder that cannot be scored; the message says what is wrong and how to fix it."""


def psnr(a: np.ndarray, b: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio in dB of two images in [0, 1], over the ``valid`` pixels [H, W] if given
    (undistorted images have corners that no pixel of the original reaches)."""
    diff = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    mse = float(np.mean(diff[valid] ** 2 if valid is not None else diff**2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


@dataclass(frozen=True)
class HeldOutView:
    """One view to score, before rendering: where its image is and how the camera saw it."""

    image: Path
    c2w: np.ndarray
    """[4, 4] camera-to-world, OpenGL camera axes, in the frame of the data file."""
    intrinsics: Intrinsics
    """Pinhole intrinsics of the image as it is on disk (nerfstudio's pixel-centre convention)."""
    dist_coeffs: np.ndarray | None = None
    """OpenCV (k1, k2, p1, p2, k3) of a distorted image; it is undistorted to ``intrinsics`` before
    scoring, because the renders are pinhole. ``None``: an ideal pinhole image."""


@dataclass(frozen=True)
class HeldOutSet:
    """The views of one split of a data folder, and the frame their poses are in."""

    format: DataFormat
    source: str
    """Where the views come from, for messages ("transforms.json test_filenames", ...)."""
    views: list[HeldOutView]
    applied_transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    """[4, 4] that nerfstudio-data folded into ``dataparser_transforms.json`` on top of what it did to the
    poses of ``transforms.json``; it is taken back out before mapping them. Identity for other runs."""
    applied_scale: float = 1.0
    """Likewise for the scale (``applied_scale`` of transforms.json)."""


@dataclass
class ViewScore:
    """One scored view."""

    file: Path
    psnr: float
    rendered: np.ndarray
    observed: np.ndarray
    """[H, W, 3] in [0, 1], over black, undistorted where the lens was distorted."""
    valid: np.ndarray | None = None
    """[H, W] pixels that count (``None``: all); undistortion leaves corners that no original pixel reaches."""

    @property
    def black_psnr(self) -> float:
        """PSNR an all-black render would score on this view."""
        return psnr(np.zeros_like(self.observed), self.observed, self.valid)


@dataclass
class SplitScore:
    """The scores of a split, with the all-black baseline that a model rendering nothing gets."""

    format: DataFormat
    split: str
    source: str
    views: list[ViewScore]
    mean_psnr: float
    """Mean over views of the per-view PSNR (dB)."""
    black_psnr: float
    """Mean over the same views of the PSNR of an all-black image (dB)."""
    margin_db: float
    """``mean_psnr - black_psnr``: how much the model beats rendering nothing."""

    @classmethod
    def of(cls, held_out: HeldOutSet, split: str, views: list[ViewScore]) -> "SplitScore":
        mean = float(np.mean([v.psnr for v in views]))
        black = float(np.mean([v.black_psnr for v in views]))
        return cls(held_out.format, split, held_out.source, views, mean, black, mean - black)


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"no {path.name} in {path.parent}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DataFormatError(f"{path} is not valid JSON: {err}") from err
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise DataFormatError(f"{path} must be a JSON object with a non-empty list of frames")
    for index, frame in enumerate(data["frames"]):
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise DataFormatError(f"{path}: frame {index} needs a file_path and a transform_matrix")
    return data


def _image_size(path: Path, source: Path) -> tuple[int, int]:
    if not path.is_file():
        raise FileNotFoundError(f"image {path} listed in {source} does not exist")
    return image_size(path)


def _pose(frame: dict, source: Path) -> np.ndarray:
    c2w = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
    if c2w.shape not in ((4, 4), (3, 4)):
        raise DataFormatError(f"{source}: frame {frame.get('file_path')!r} needs a 4x4 transform_matrix")
    return np.vstack([c2w[:3], [0.0, 0.0, 0.0, 1.0]])


def blender_views(data_dir: Path, split: str = "test") -> HeldOutSet:
    """``transforms_<split>.json`` read as nerfstudio's ``blender-data`` reads it: ``<file_path>.png``,
    focal length from ``camera_angle_x``, principal point at the image centre."""
    data_dir = Path(data_dir)
    path = data_dir / f"transforms_{split}.json"
    meta = _read_json(path)
    if "camera_angle_x" not in meta:
        raise DataFormatError(f"{path} has no camera_angle_x; Blender transforms files give the field of view")
    views = []
    for frame in meta["frames"]:
        image = data_dir / (str(frame["file_path"]).removeprefix("./") + ".png")
        width, height = _image_size(image, path)
        focal = 0.5 * width / np.tan(0.5 * float(meta["camera_angle_x"]))
        views.append(HeldOutView(image, _pose(frame, path), Intrinsics(focal, focal, width / 2, height / 2,
                                                                         width, height)))
    return HeldOutSet("blender", path.name, views)


def nerfstudio_split(meta: dict, image_filenames: list[Path], data_dir: Path, split: str,
                     parser: NerfstudioDataParserConfig) -> tuple[np.ndarray, str]:
    """Indices into ``image_filenames`` (sorted, as nerfstudio-data sorts them) of one split, and where
    the split comes from. The rules are nerfstudio-data's: the file's ``<split>_filenames`` when it has
    any split lists, otherwise its ``eval_mode`` through nerfstudio's own split functions. Held-out
    splits (val, test) also take the other held-out list when the file gives only that one."""
    keys = [f"{split}_filenames"] + {"val": ["test_filenames"], "test": ["val_filenames"]}.get(split, [])
    for key in keys:
        if key in meta:
            wanted = {data_dir / Path(name) for name in meta[key]}
            unknown = sorted(wanted.difference(image_filenames))
            if unknown:
                raise DataFormatError(f"transforms.json: {len(unknown)} names in {key} are not frames of the file, "
                                      f"e.g. {unknown[0]}")
            return np.array([i for i, name in enumerate(image_filenames) if name in wanted], dtype=int), key
    listed = [f"{s}_filenames" for s in BLENDER_SPLITS if f"{s}_filenames" in meta]
    if listed:
        raise DataFormatError(f"transforms.json lists {', '.join(listed)} but no {split} views; score another "
                              f"--split")
    mode = parser.eval_mode
    try:
        if mode == "fraction":
            i_train, i_eval = get_train_eval_split_fraction(image_filenames, parser.train_split_fraction)
            rule = f"eval-mode fraction, train-split-fraction {parser.train_split_fraction}"
        elif mode == "filename":
            i_train, i_eval = get_train_eval_split_filename(image_filenames)
            rule = "eval-mode filename"
        elif mode == "interval":
            i_train, i_eval = get_train_eval_split_interval(image_filenames, parser.eval_interval)
            rule = f"eval-mode interval, eval-interval {parser.eval_interval}"
        elif mode == "all":
            i_train, i_eval = get_train_eval_split_all(image_filenames)
            rule = "eval-mode all"
        else:
            raise DataFormatError(f"the run's nerfstudio-data eval-mode {mode!r} is unknown here")
    except ValueError as err:  # eval-mode filename: a name with neither train nor eval in it
        raise DataFormatError(f"transforms.json cannot be split by {mode}: {err}") from err
    return np.asarray(i_train if split == "train" else i_eval, dtype=int), f"nerfstudio-data {split} split ({rule})"


def _nerfstudio_distortion(frame: dict, meta: dict, source: Path) -> np.ndarray | None:
    """OpenCV (k1, k2, p1, p2, k3) of a frame, read as nerfstudio-data reads it (the file's top-level
    coefficients, when it has any, for every frame); ``None`` when all are zero."""
    keys = ("k1", "k2", "k3", "k4", "p1", "p2", "distortion_params")
    holder = meta if any(key in meta for key in keys) else frame
    if "distortion_params" in holder:
        params = np.asarray(holder["distortion_params"], dtype=np.float64).ravel()
        if params.size != 6:
            raise DataFormatError(f"{source}: distortion_params must be nerfstudio's 6 numbers "
                                  f"(k1, k2, k3, k4, p1, p2), got {params.size}")
        k1, k2, k3, k4, p1, p2 = params
    else:
        k1, k2, k3, k4, p1, p2 = (float(holder.get(key, 0.0)) for key in keys[:6])
    if k4 != 0:
        raise DataFormatError(f"{source}: k4 = {k4} is not supported (nerfstudio's r^8 term has no OpenCV "
                              f"counterpart to undistort the images with); undistort them first")
    dist = np.array([k1, k2, p1, p2, k3])
    return dist if np.any(dist) else None


def nerfstudio_views(data_dir: Path, split: str = "test",
                     parser: NerfstudioDataParserConfig | None = None) -> HeldOutSet:
    """A nerfstudio ``transforms.json`` read as ``nerfstudio-data`` reads it: frames sorted by file name,
    split by its file lists or by ``parser``'s rule (nerfstudio's defaults when ``None``), intrinsics at
    the top level or per frame (top level wins), poses OpenGL camera-to-world in the file's frame.

    When the run itself was trained by nerfstudio-data (``parser`` given), the file's ``applied_transform``
    and ``applied_scale`` are recorded: nerfstudio folds them into ``dataparser_transforms.json`` although
    it never applied them to these poses."""
    given = Path(data_dir)
    path = given if given.suffix == ".json" else given / "transforms.json"
    data_dir = path.parent
    meta = _read_json(path)
    camera_model = meta.get("camera_model", "OPENCV")
    if camera_model not in PINHOLE_CAMERA_MODELS:
        raise DataFormatError(f"{path}: camera_model {camera_model} is not a pinhole camera; only "
                              f"{', '.join(PINHOLE_CAMERA_MODELS)} can be scored")
    names = [data_dir / Path(frame["file_path"]) for frame in meta["frames"]]
    order = np.argsort(names)  # nerfstudio sorts the frames by file name before splitting them
    frames, names = [meta["frames"][i] for i in order], [names[i] for i in order]
    indices, source = nerfstudio_split(meta, names, data_dir, split, parser or NerfstudioDataParserConfig())
    if len(indices) == 0:
        raise DataFormatError(f"{path}: the {source} holds no views ({len(frames)} frames in all)")
    views = []
    for i in indices:
        frame = frames[i]
        missing = [key for key in ("fl_x", "fl_y", "cx", "cy", "w", "h") if key not in meta and key not in frame]
        if missing:
            raise DataFormatError(f"{path}: frame {frame['file_path']!r} has no {', '.join(missing)} and the file "
                                  f"gives none at the top level")
        value = {key: float(meta[key] if key in meta else frame[key]) for key in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
        intrinsics = Intrinsics(value["fl_x"], value["fl_y"], value["cx"], value["cy"], int(value["w"]),
                                int(value["h"]))
        size = _image_size(names[i], path)
        if size != (intrinsics.width, intrinsics.height):
            intrinsics = intrinsics.scaled(*size)  # a downscaled copy of the images: the same camera
        views.append(HeldOutView(names[i], _pose(frame, path), intrinsics, _nerfstudio_distortion(frame, meta, path)))
    applied, scale = np.eye(4), 1.0
    if parser is not None:
        if "applied_transform" in meta:
            applied[:3] = np.asarray(meta["applied_transform"], dtype=np.float64)
        elif (given / "colmap" / "sparse" / "0").exists():  # as nerfstudio checks it, under --data
            applied[:3] = LEGACY_COLMAP_TRANSFORM
        scale = float(meta.get("applied_scale", 1.0))
    return HeldOutSet("nerfstudio", f"{path.name} {source}", views, applied, scale)


def speedplus_views(data_dir: Path, split: str = "test",
                    parser: SpeedPlusDataParserConfig | None = None) -> HeldOutSet:
    """The labelled views ``speedplus-data`` gives for ``split``, through its own functions: the same label
    file, held-out part and eval-count subset (the run's settings when ``parser`` is given), the same
    label-to-pose conversion, metres in the Tango body frame (the run's scale is applied by the loader)."""
    config = (dataclasses.replace(parser, data=Path(data_dir)) if parser is not None
              else SpeedPlusDataParserConfig(data=Path(data_dir)))
    try:
        camera = read_camera(config.data)
        labels, source = select_labels(config, split)
        paths = image_paths(config.data, config.domain, labels, camera, source)
        poses = [label_c2w_opengl(label) for label in labels]
    except ValueError as err:
        raise DataFormatError(str(err)) from err
    intrinsics = Intrinsics.from_opencv(camera.matrix, camera.width, camera.height)
    dist = camera.dist_coeffs if np.any(camera.dist_coeffs) else None
    return HeldOutSet("speedplus", source, [HeldOutView(p, c2w, intrinsics, dist) for p, c2w in zip(paths, poses)])


def detect_format(data_dir: Path) -> DataFormat:
    """The layout of a data folder, from the files in it: Blender transforms files first (a folder
    ``ns-invert-synth`` writes holds both those and a ``transforms.json``), then nerfstudio's, then SPEED+."""
    data_dir = Path(data_dir)
    if data_dir.is_file() and data_dir.suffix == ".json":
        return "nerfstudio"
    if not data_dir.is_dir():
        raise FileNotFoundError(f"--data {data_dir} is not a folder")
    if any((data_dir / f"transforms_{split}.json").is_file() for split in BLENDER_SPLITS):
        return "blender"
    if (data_dir / "transforms.json").is_file():
        return "nerfstudio"
    if (data_dir / "synthetic" / "validation.json").is_file() or (
            (data_dir / "camera.json").is_file() and any((data_dir / d).is_dir() for d in SPEEDPLUS_DOMAINS)):
        return "speedplus"
    raise DataFormatError(f"cannot tell the format of {data_dir}: it holds no transforms_<split>.json (Blender), "
                          f"transforms.json (nerfstudio), synthetic/validation.json or camera.json with a domain "
                          f"folder (SPEED+); pass the folder the run was trained on, or --format")


def run_dataparser(loaded: LoadedModel | None) -> object | None:
    """The dataparser config the run was trained with, when the loaded config holds one."""
    pipeline = getattr(getattr(loaded, "config", None), "pipeline", None)
    return getattr(getattr(pipeline, "datamanager", None), "dataparser", None)


def read_held_out(data_dir: Path, data_format: FormatChoice = "auto", split: str = "test",
                  parser: object | None = None, max_views: int | None = None) -> HeldOutSet:
    """The views of ``split`` in ``data_dir``, read in ``data_format`` (detected under ``auto``).
    ``parser`` is the run's dataparser config: its split settings apply when it is of the same kind as the
    format. ``max_views`` keeps that many, spread evenly (SPEED+ validation holds 11,994 images)."""
    fmt = detect_format(data_dir) if data_format == "auto" else data_format
    if fmt == "blender":
        held_out = blender_views(data_dir, split)
    elif fmt == "nerfstudio":
        held_out = nerfstudio_views(data_dir, split, parser if isinstance(parser, NerfstudioDataParserConfig) else None)
    elif fmt == "speedplus":
        held_out = speedplus_views(data_dir, split, parser if isinstance(parser, SpeedPlusDataParserConfig) else None)
    else:
        raise DataFormatError(f"unknown format {fmt!r}; choose auto, blender, nerfstudio or speedplus")
    if max_views is not None:
        if max_views < 1:
            raise DataFormatError(f"--max-views must be at least 1, got {max_views}")
        if max_views < len(held_out.views):
            kept = [held_out.views[i] for i in evenly_spaced(max_views, len(held_out.views))]
            held_out = dataclasses.replace(held_out, views=kept,
                                           source=f"{held_out.source}, {max_views} of {len(held_out.views)} views")
    return held_out


def model_poses(loaded: LoadedModel, held_out: HeldOutSet) -> np.ndarray:
    """[N, 4, 4] model-frame poses of the views, through the run's ``dataset_to_model``, after taking out
    what nerfstudio-data recorded there but never applied to the file's poses (identity for other runs)."""
    frame = loaded
    if not np.allclose(held_out.applied_transform, np.eye(4)) or held_out.applied_scale != 1.0:
        frame = dataclasses.replace(
            loaded, dataparser_transform=loaded.dataparser_transform @ np.linalg.inv(held_out.applied_transform),
            dataparser_scale=loaded.dataparser_scale / held_out.applied_scale)
    return frame.dataset_to_model(np.stack([view.c2w for view in held_out.views]))


def undistort(image: np.ndarray, intrinsics: Intrinsics, dist_coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The image a pinhole camera with the same intrinsics would take (as the inversion's sequences undistort
    theirs), and the [H, W] mask of pixels whose source lies inside the original image."""
    matrix = np.array([[intrinsics.fx, 0, intrinsics.cx - 0.5], [0, intrinsics.fy, intrinsics.cy - 0.5], [0, 0, 1]])
    size = (intrinsics.width, intrinsics.height)
    map_x, map_y = cv2.initUndistortRectifyMap(matrix, np.asarray(dist_coeffs, np.float64), None, matrix, size,
                                               cv2.CV_32FC1)
    out = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    valid = (map_x >= 0) & (map_x <= size[0] - 1) & (map_y >= 0) & (map_y <= size[1] - 1)
    return out, valid


def score_views(loaded: LoadedModel, held_out: HeldOutSet) -> list[ViewScore]:
    """Render every view at its model-frame pose and score it against its image (over black)."""
    scores = []
    for view, c2w in zip(held_out.views, model_poses(loaded, held_out)):
        try:
            observed, valid = read_rgb_over_black(view.image), None
        except ImageError as err:
            raise DataFormatError(f"{err}; replace it with a readable image") from err
        if observed.shape[:2] != (view.intrinsics.height, view.intrinsics.width):
            raise DataFormatError(f"image {view.image} is {observed.shape[1]}x{observed.shape[0]}, not the "
                                  f"{view.intrinsics.width}x{view.intrinsics.height} its camera says")
        if view.dist_coeffs is not None:
            observed, valid = undistort(observed, view.intrinsics, view.dist_coeffs)
        rendered = render_image(loaded, c2w, view.intrinsics)
        scores.append(ViewScore(view.image, psnr(rendered, observed, valid), rendered, observed, valid))
    return scores


def score_split(loaded: LoadedModel, data_dir: Path, data_format: FormatChoice = "auto", split: str = "test",
                max_views: int | None = None) -> SplitScore:
    """Score a trained run on the held-out views of its data, whatever dataparser it was trained with;
    the run's own dataparser settings (split rule, SPEED+ domain and eval-count) apply where they can."""
    held_out = read_held_out(data_dir, data_format, split, run_dataparser(loaded), max_views)
    return SplitScore.of(held_out, split, score_views(loaded, held_out))


def evaluate_split(loaded: LoadedModel, data_dir: Path, split: str = "test") -> list[ViewScore]:
    """Render every view of ``transforms_<split>.json`` and score it against its image.

    Poses in the file are in the dataset frame and are mapped through the run's dataparser transform,
    so this also checks that the model frame is what ``dataparser_transforms.json`` says it is.
    """
    return score_views(loaded, blender_views(data_dir, split))

