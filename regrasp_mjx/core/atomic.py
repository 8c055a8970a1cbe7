"""Files written whole or not at all: a temporary file in the same folder, then an atomic rename,
so a killed process never leaves a half-written checkpoint, policy, dataset or log; an experiment's
results (a table and its rows) and the machine they were measured on."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import platform
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import jax
import numpy as np


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


def output_file_problem(path: str | os.PathLike, suffix: str | None = None) -> str | None:
    """Why ``path`` cannot be written as a file by :func:`atomic_write` (None when it can): CLIs
    check their ``--out`` before any work, so a bad path costs no minutes of computing."""
    if not str(path).strip():
        return f"--out '' is not accepted: a file path ({suffix or 'any name'})"
    path = Path(path)
    if suffix is not None and path.suffix != suffix:
        return f"--out {path} is not accepted: a file path ending in {suffix}"
    if path.is_dir():
        return f"--out {path} is a folder; accepted: a file path ({suffix or 'any name'}) in a writable folder"
    parent = _unwritable(path.parents)
    if parent is not None:
        return f"--out {path}: {parent} is not a writable folder; accepted: a file path in a folder this user can write"
    if not path.parent.is_dir():  # a typo in a folder name should not leave a new folder behind
        return f"--out {path}: the folder {path.parent} does not exist; accepted: a file path in an existing folder"
    return None


def output_folder_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be the folder a command writes its results into (None when it can):
    checked before any work, as :func:`output_file_problem` checks a file."""
    if not str(path).strip():
        return "--out '' is not accepted: a folder path (an empty one would write into the current folder)"
    path = Path(path)
    if path.exists() and not path.is_dir():
        return f"--out {path} is a file; accepted: a folder"
    parent = _unwritable((path, *path.parents))
    if parent is not None:
        return f"--out {path}: {parent} is not a writable folder; accepted: a folder this user can write"
    return None


def _unwritable(candidates) -> Path | None:
    """The nearest existing of ``candidates`` (a path and its parents) when it is no folder this user
    can write into, else None: atomic_write and the folders' users create the missing ones below it.
    Tried by writing (and removing) an empty file there: ``os.access`` says yes to root for folders
    no one can write, such as ``/proc``."""
    parent = next((p for p in candidates if p.exists()), Path("."))
    if not (parent.is_dir() and os.access(parent, os.W_OK | os.X_OK)):
        return parent
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".write_probe", suffix=".tmp")
    except OSError:
        return parent
    os.close(fd)
    os.unlink(probe)
    return None


def strict(obj: Any) -> Any:
    """``obj`` with every float that is not finite (NaN, infinity) as None, numpy scalars and
    arrays as plain Python: what strict JSON (RFC 8259) can hold, a missing value as ``null``."""
    if isinstance(obj, dict):
        return {k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if isinstance(obj, (np.ndarray, np.generic)):
        return strict(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj: Any, **options: Any) -> str:
    """``json.dumps`` of :func:`strict` ``obj``, refusing anything else non-standard: every JSON
    this project writes or prints goes through here."""
    return json.dumps(strict(obj), allow_nan=False, **options)


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    atomic_write(path, lambda f: f.write(dumps(obj, indent=indent).encode()))


def write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode()))


def write_figure(path: str | os.PathLike, figure: Any, dpi: int = 120, **savefig: Any) -> None:
    """A matplotlib figure saved whole to ``path`` (format from its suffix, PNG by default)."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    atomic_write(path, lambda f: figure.savefig(f, format=fmt, dpi=dpi, **savefig))


def write_csv(path: str | os.PathLike, header: list[str], rows: Any) -> None:
    """A CSV file of a ``header`` and ``rows`` (sequences in its order), written whole."""

    text = io.StringIO(newline="")
    writer = csv.writer(text)
    writer.writerow(header)
    writer.writerows(rows)
    write_text(path, text.getvalue())


def write_results(out: str | os.PathLike | None, name: str, lines: list[str], data: Any) -> None:
    """An experiment's results: ``OUT/NAME.md`` (a table's lines, for people) and ``OUT/NAME.json``
    (``data``, for scripts), each written atomically; nothing when ``out`` is None."""
    if out is None:
        return
    write_text(Path(out) / f"{name}.md", "\n".join(lines) + "\n")
    write_json(Path(out) / f"{name}.json", data)


def machine(devices: bool = True) -> str:
    """What a result was measured on: the CPU's model, the host and its cores, and (``devices``)
    JAX's backend and first device; a result file names it beside its numbers."""
    try:
        cpu = open("/proc/cpuinfo").read().split("model name")[1].split(":")[1].split("\n")[0].strip()
    except (OSError, IndexError):  # not Linux
        cpu = platform.processor() or platform.machine()
    where = f"{cpu} ({platform.node()}, {os.cpu_count()} cores)"
    return f"{where}; {jax.default_backend()}: {jax.devices()[0].device_kind}" if devices else where
