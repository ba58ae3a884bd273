"""``python -m nerfinv_plugin.cli.lightbox_gap``: render SHIRT trajectories in the synthetic and the
lightbox-like domain and print, per frame, the PSNR between the two and the object mask's IoU."""

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from rich.console import Console

from nerfinv_plugin.cli import run
from nerfinv_plugin.inversion.validation import SettingsError, check, whole
from nerfinv_plugin.results.atomic import write_atomic
from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.lightbox_domain import write_lightbox_domain
from nerfinv_plugin.synth.lightbox_gap import frame_gaps
from nerfinv_plugin.synth.scenes import SceneName
from nerfinv_plugin.synth.trajectories import TrajectoryKind, TrajectoryMotion, TrajectorySpec

RULES = {"seed": whole(0), "spp": whole(1), "num-frames": whole(1), "width": whole(1), "height": whole(1)}
"""What the numeric options accept (nerfinv_plugin/inversion/validation.py)."""


@dataclass
class LightboxGap:
    """Render the default SHIRT trajectories of a scene (undistorted) in both domains into ``<out>/shirt``,
    as ``ns-invert-synth --trajectory.lightbox`` does, then print per frame the PSNR of the lightbox image
    against the synthetic one and the IoU of the object mask found on the lightbox image (find_object)
    with the object's alpha and with the mask found on a clean render of the lab lighting. Writes the
    numbers to ``<out>/lightbox-gap.json``."""

    out: Path
    """Output folder."""
    scene: SceneName = "tango"
    """tango: the spacecraft; toy: the tabletop object."""
    seed: int = 0
    """The generator's seed (textures, attitudes, render and camera noise)."""
    spp: int = 64
    """Samples per pixel of every render."""
    kinds: tuple[TrajectoryKind, ...] = ("roe1", "roe2")
    """Trajectories to render."""
    num_frames: int = 20
    """Frames per trajectory."""
    width: int = 240
    """Image width in pixels."""
    height: int = 150
    """Image height in pixels."""

    def main(self) -> None:
        check(self, RULES)
        console = Console(soft_wrap=True)  # one line a frame, however narrow the terminal
        motion = TrajectoryMotion(num_frames=self.num_frames)
        specs = [TrajectorySpec.of(kind, motion) for kind in self.kinds]
        camera = speedplus_like_camera(self.width, self.height)
        with console.status(f"rendering {self.scene} in both domains"):
            synthetic = write_shirt_trajectories(self.out, self.scene, specs, camera, False, self.seed, self.spp,
                                                 lambda: None)
            lightbox = write_lightbox_domain(self.out, self.scene, synthetic, camera, False, self.seed, self.spp,
                                             lambda: None)
            gaps = frame_gaps(self.scene, self.seed, synthetic, lightbox, camera, self.spp)
        for gap in gaps:
            console.print(f"{gap.trajectory}/{gap.filename}: PSNR {gap.psnr_db:.2f} dB; mask IoU with alpha "
                          f"{gap.iou_alpha:.3f}, with the clean render's mask {gap.iou_clean:.3f} (clean render "
                          f"with alpha {gap.clean_iou_alpha:.3f}, synthetic image with alpha "
                          f"{gap.synthetic_iou_alpha:.3f})")
        for kind in self.kinds:
            mine = [g for g in gaps if g.trajectory == kind]
            console.print(f"{kind}: PSNR median {np.median([g.psnr_db for g in mine]):.2f} dB; IoU with alpha "
                          f"median {np.median([g.iou_alpha for g in mine]):.3f} (min "
                          f"{min(g.iou_alpha for g in mine):.3f}); with the clean render's mask median "
                          f"{np.median([g.iou_clean for g in mine]):.3f} (min {min(g.iou_clean for g in mine):.3f})")
        write_atomic(self.out / "lightbox-gap.json",
                     json.dumps({"settings": asdict(self), "frames": [asdict(g) for g in gaps]}, indent=2,
                                default=str))


def entrypoint() -> None:
    run(LightboxGap, "lightbox-gap", SettingsError, OSError, ValueError)


if __name__ == "__main__":
    entrypoint()
