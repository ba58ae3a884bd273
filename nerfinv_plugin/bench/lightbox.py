"""The lightbox-like domain against the synthetic one: render SHIRT trajectories of a scene (undistorted) in
both domains, as ``ns-invert-synth --trajectory.lightbox`` does, and measure each frame's gap
(:mod:`nerfinv_plugin.synth.lightbox_gap`), with a summary per trajectory."""

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfinv_plugin.synth.datasets import speedplus_like_camera, write_shirt_trajectories
from nerfinv_plugin.synth.lightbox_domain import write_lightbox_domain
from nerfinv_plugin.synth.lightbox_gap import FrameGap, frame_gaps
from nerfinv_plugin.synth.scenes import SceneName
from nerfinv_plugin.synth.trajectories import TrajectoryKind, TrajectoryMotion, TrajectorySpec


@dataclass(frozen=True)
class TrajectoryGap:
    """The frames of one trajectory, summarised."""

    trajectory: str
    psnr_median_db: float
    iou_alpha_median: float
    iou_alpha_min: float
    iou_clean_median: float
    iou_clean_min: float


def domain_gaps(out: Path, scene: SceneName, kinds: Sequence[TrajectoryKind], num_frames: int, width: int,
                height: int, seed: int, spp: int) -> list[FrameGap]:
    """Write the trajectories ``kinds`` in both domains into ``<out>/shirt`` and return every frame's gap."""
    specs = [TrajectorySpec.of(kind, TrajectoryMotion(num_frames=num_frames)) for kind in kinds]
    camera = speedplus_like_camera(width, height)
    synthetic = write_shirt_trajectories(out, scene, specs, camera, False, seed, spp, lambda: None)
    lightbox = write_lightbox_domain(out, scene, synthetic, camera, False, seed, spp, lambda: None)
    return frame_gaps(scene, seed, synthetic, lightbox, camera, spp)


def by_trajectory(gaps: Sequence[FrameGap]) -> list[TrajectoryGap]:
    """Medians (and minimum IoUs) of each trajectory's frames, in the order the trajectories come."""
    names = list(dict.fromkeys(g.trajectory for g in gaps))
    summaries = []
    for name in names:
        mine = [g for g in gaps if g.trajectory == name]
        alpha, clean = [g.iou_alpha for g in mine], [g.iou_clean for g in mine]
        summaries.append(TrajectoryGap(name, float(np.median([g.psnr_db for g in mine])), float(np.median(alpha)),
                                       min(alpha), float(np.median(clean)), min(clean)))
    return summaries
