"""``ns-invert-demo``: the whole pipeline on the synthetic spacecraft in one command."""

import dataclasses
import time
from dataclasses import dataclass

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from nerfinv_plugin.cli import run
from nerfinv_plugin.cli.invert import BAD_INPUT, invert
from nerfinv_plugin.cli.synth import TRAINING_SET_RULES
from nerfinv_plugin.demo import (
    DemoSettings,
    data_rendered,
    inversion_finished,
    model_trained,
    render_data,
    train_model,
)
from nerfinv_plugin.inversion.validation import INVERT_RULES, check, under, whole
from nerfinv_plugin.results.folder import CONFIG

RULES = {
    "frames": whole(1), "training-iterations": whole(1), "iterations": whole(1), "seed": whole(0),
    **under("training-set", TRAINING_SET_RULES), "training-set.train-views": whole(1),  # the demo trains on them
    **{name: rule for name, rule in INVERT_RULES.items() if name.startswith(("starts.", "render."))},
}
"""What the numeric options accept: the starts and render options as ns-invert's
(nerfinv_plugin/inversion/validation.py)."""


@dataclass
class Demo(DemoSettings):
    """Render the synthetic spacecraft (a NeRF training set and a 'roe1' trajectory in the SHIRT format),
    train nerfacto-tiny on it, and estimate the pose in every frame of the trajectory with ns-invert. About
    10 minutes on a 2-core CPU the first time; a second run reuses every finished stage (an interrupted
    inversion continues where it stopped)."""

    def main(self) -> None:
        check(self, RULES)
        console, s = Console(), self
        tic = time.perf_counter()
        spec = s.training_set
        total = spec.train_views + spec.val_views + spec.test_views + s.frames
        columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
        if data_rendered(s):
            console.print(f"1/3 data in {s.data_dir} (already rendered)")
        else:
            with Progress(*columns, console=console) as progress:
                task = progress.add_task("1/3 rendering the synthetic spacecraft", total=total)
                render_data(s, lambda: progress.advance(task))
        if model_trained(s):
            console.print(f"2/3 model {s.model_config} (already trained)")
        else:
            with Progress(*columns, console=console) as progress:
                task = progress.add_task("2/3 training nerfacto-tiny on the CPU", total=s.training_iterations)
                train_model(s, lambda step: progress.update(task, completed=step + 1))
        if inversion_finished(s):
            console.print(f"3/3 inversion already finished: {s.run_dir}")
        else:
            config = s.inversion()
            if (s.run_dir / CONFIG).is_file():
                config = dataclasses.replace(config, resume=s.run_dir)
            console.print("3/3 inverting the roe1 trajectory")
            invert(config, console)
        console.print(f"[green]done in {time.perf_counter() - tic:.0f} s; results in {s.run_dir}[/green]")


def entrypoint() -> None:
    run(Demo, "ns-invert-demo", *BAD_INPUT, OSError)


if __name__ == "__main__":
    entrypoint()
