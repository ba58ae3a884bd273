"""Training ``nerfacto-tiny`` in-process, for the test fixture and the demo.

``ns-train`` does the same from the shell; in-process training avoids a second interpreter start and
lets a caller put its own limits (iterations, rays) on the stock configuration.
"""

import copy
from collections.abc import Callable
from pathlib import Path
from typing import Literal

from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

from nerfinv_plugin.model.nerfacto_tiny import nerfacto_tiny


def train_nerfacto_tiny(data: Path, output_dir: Path, experiment_name: str, iterations: int,
                        rays_per_batch: int = 512, timestamp: str = "run",
                        on_iteration: Callable[[int], None] | None = None,
                        dataparser: Literal["blender-data", "nerfstudio-data"] = "blender-data") -> Path:
    """Train on a Blender-format dataset (or, with ``dataparser="nerfstudio-data"``, a nerfstudio
    ``transforms.json`` read with nerfstudio's defaults, as ``ns-train ... nerfstudio-data`` does) and return
    the ``config.yml`` of the run. ``on_iteration(step)`` is called after every training iteration.

    Call it under ``if __name__ == "__main__":`` in scripts: nerfstudio may start worker processes with
    the ``spawn`` method, which re-imports the calling module (nerfacto-tiny itself starts none).
    """
    config = copy.deepcopy(nerfacto_tiny.config)
    if dataparser == "nerfstudio-data":
        config.pipeline.datamanager.dataparser = NerfstudioDataParserConfig()
    config.pipeline.datamanager.data = Path(data)
    config.pipeline.datamanager.train_num_rays_per_batch = rays_per_batch
    config.output_dir = Path(output_dir)
    config.experiment_name = experiment_name
    config.timestamp = timestamp
    config.max_num_iterations = iterations
    config.steps_per_save = iterations
    for group in config.optimizers.values():
        group["scheduler"].max_steps = iterations
    config.logging.local_writer.enable = False
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    if on_iteration is not None:
        trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                                                  lambda step: on_iteration(step), update_every_num_iters=1))
    trainer.train()
    return config.get_base_dir() / "config.yml"
