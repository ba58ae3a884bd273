"""A rendered training set as a camera delivers it: RGB images over black, no alpha (SPEED+, SHIRT and
real captures look like this), with a nerfstudio ``transforms.json`` for ``ns-train ... nerfstudio-data``."""

import json
from pathlib import Path

import cv2
import numpy as np

from nerfinv_plugin.synth.datasets import write_image, write_json_atomic


def write_camera_images(out: Path, rgb_dir: Path) -> None:
    """The training set under ``out`` as a camera delivers it: RGB JPEG images over black, no alpha, and a
    nerfstudio ``transforms.json`` (the same poses, intrinsics and splits) for ``nerfstudio-data``."""
    meta = json.loads((out / "transforms.json").read_text())
    renamed = {}
    for index, frame in enumerate(meta["frames"]):
        rgba = cv2.imread(str(out / frame["file_path"]), cv2.IMREAD_UNCHANGED)
        if rgba is None:
            raise OSError(f"cannot read {out / frame['file_path']}")
        rgb = rgba[..., :3].astype(np.float32) * (rgba[..., 3:] / 255.0) if rgba.shape[2] == 4 else rgba
        name = f"images/frame_{index:05d}.jpg"
        write_image(rgb_dir / name, cv2.cvtColor((rgb + 0.5).astype(np.uint8), cv2.COLOR_BGR2RGB))
        renamed[frame["file_path"]] = name
    copy = {key: [renamed[n] for n in value] if key.endswith("_filenames") else value
            for key, value in meta.items() if key != "frames"}
    copy["frames"] = [{**frame, "file_path": renamed[frame["file_path"]]} for frame in meta["frames"]]
    write_json_atomic(rgb_dir / "transforms.json", copy)
