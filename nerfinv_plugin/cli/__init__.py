"""Thin tyro front ends: each builds a dataclass from the command line and calls its ``main``."""

import signal
import sys
import warnings
from typing import Any

import tyro
from rich.console import Console
from rich.markup import escape

# torch and nerfstudio deprecation notices on import say nothing to a user of these commands.
warnings.filterwarnings("ignore", category=FutureWarning)
warnings.filterwarnings("ignore", category=UserWarning, module="nerfstudio")


def _stop(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


class Interrupted(Exception):
    """Ctrl-C during long work; the message says what was kept and how to continue."""


def run(command: type, name: str, *expected: type[BaseException], default: Any = None) -> None:
    """Parse ``command`` from the command line (starting from ``default`` when given) and run it. The
    ``expected`` errors are bad input, not bugs: they end the program with their one-line message and exit
    code 2, without a traceback. Ctrl-C ends it with exit code 130."""
    tyro.extras.set_accent_color("bright_yellow")
    errors = Console(stderr=True, soft_wrap=True)  # one line, however long
    signal.signal(signal.SIGTERM, _stop)  # `kill` stops a background run as Ctrl-C does, keeping its results
    try:
        parsed: Any = tyro.cli(command, default=default)
        parsed.main()
    except expected as err:
        errors.print(f"[red]{name}: {escape(str(err))}[/red]")
        sys.exit(2)
    except (Interrupted, KeyboardInterrupt) as err:
        errors.print(f"[red]{name}: {escape(str(err) or 'interrupted')}[/red]")
        sys.exit(130)
