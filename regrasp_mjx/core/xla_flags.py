"""How this package's programs are compiled: the XLA flags they run best with, added to
``XLA_FLAGS`` when the package is imported (before JAX starts a backend, which reads them once),
and the compilation cache its commands share (:func:`cache_folder`).

On a GPU the continuous collision test walks intervals in loops whose trip counts the data decide
(:mod:`regrasp_mjx.world.continuous`); XLA runs each loop iteration from the host, copying its
predicate back and waiting for it, unless its while loops and conditionals are recorded into CUDA
graphs, where they run on the device (CUDA's conditional graph nodes). Measured on one H100: 30.1 ->
36.4 M env-steps/s at 32,768 environments, 10.0 -> 16.1 M at 8,192, and 42 -> 12 copies to the host
a step (experiments/RESULTS.md, "Fewer waits for the device"). On a CPU the flags do nothing.

Flags already in the user's ``XLA_FLAGS`` are kept as given; ``REGRASP_MJX_XLA_FLAGS=0`` leaves
``XLA_FLAGS`` alone. Set by a program that started JAX's backend before importing this package,
they do not apply.

Every command (:func:`regrasp_mjx.core.host_loop.run_command`) keeps its compiled programs in one
persistent cache, so a process that compiles what another already has loads it instead: a recipe's
students and candidates are the same programs on other data (:mod:`regrasp_mjx.core.jobs` starts
one of them first and the rest once it has compiled).
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path

FLAGS = ("--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL", "--xla_gpu_graph_min_graph_size=1")
OPT_OUT = "REGRASP_MJX_XLA_FLAGS"
CACHE = "REGRASP_JAX_CACHE"  # the cache's folder; JAX's own JAX_COMPILATION_CACHE_DIR wins over it


def apply(environ: MutableMapping[str, str] = os.environ) -> str:
    """Adds each of :data:`FLAGS` whose name ``XLA_FLAGS`` does not already set (unless
    ``REGRASP_MJX_XLA_FLAGS=0``); returns ``XLA_FLAGS`` as it then is."""
    current = environ.get("XLA_FLAGS", "")
    if environ.get(OPT_OUT, "1").strip() == "0":
        return current
    named = {word.split("=", 1)[0] for word in current.split()}
    add = [flag for flag in FLAGS if flag.split("=", 1)[0] not in named]
    if add:
        environ["XLA_FLAGS"] = " ".join([current, *add]).strip()
    return environ.get("XLA_FLAGS", "")


def cache_folder(environ: MutableMapping[str, str] = os.environ) -> str:
    """The persistent compilation cache's folder: ``JAX_COMPILATION_CACHE_DIR`` if set, else
    ``REGRASP_JAX_CACHE``, else ``~/.cache/regrasp_mjx/jax``."""
    return (
        environ.get("JAX_COMPILATION_CACHE_DIR")
        or environ.get(CACHE)
        or str(Path.home() / ".cache" / "regrasp_mjx" / "jax")
    )
