"""Thin tyro front ends: each builds a dataclass from the command line and calls its ``main``."""

import sys
from typing import Any

import tyro
from rich.console import Console


def run(command: type, name: str, *expected: type[BaseException]) -> None:
    """Parse ``command`` from the command line and run it. The ``expected`` errors are bad input, not
    bugs: they end the program with their one-line message and exit code 2, without a traceback."""
    tyro.extras.set_accent_color("bright_yellow")
    parsed: Any = tyro.cli(command)
    try:
        parsed.main()
    except expected as err:
        Console(stderr=True).print(f"[red]{name}: {err}[/red]")
        sys.exit(2)
