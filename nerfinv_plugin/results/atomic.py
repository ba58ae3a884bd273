"""Files written so that an interruption at any moment leaves the old file or the new one, never half."""

import os
from pathlib import Path


def write_atomic(path: Path, content: str | bytes) -> None:
    """Write ``content`` (text as UTF-8) through a temporary file beside ``path``, flushed to disk, and a
    rename: readers see the old file or the new one. Makes the parent folders that are missing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(content.encode() if isinstance(content, str) else content)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
