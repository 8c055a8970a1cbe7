"""Files written whole or not at all: a temporary file in the same folder, then an atomic rename,
so a killed process never leaves a half-written checkpoint, policy, dataset or log."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def atomic_write(path: str | os.PathLike, write: Callable[[IO[bytes]], Any]) -> None:
    """Calls ``write(f)`` on a binary file that replaces ``path`` only once ``write`` returned."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    atomic_write(path, lambda f: f.write(json.dumps(obj, indent=indent).encode()))


def write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode()))


def write_results(out: str | os.PathLike | None, name: str, lines: list[str], data: Any) -> None:
    """An experiment's results: ``OUT/NAME.md`` (a table's lines, for people) and ``OUT/NAME.json``
    (``data``, for scripts), each written atomically; nothing when ``out`` is None."""
    if out is None:
        return
    write_text(Path(out) / f"{name}.md", "\n".join(lines) + "\n")
    write_json(Path(out) / f"{name}.json", data)
