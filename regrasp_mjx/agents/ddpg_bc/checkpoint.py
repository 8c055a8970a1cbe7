"""Checkpoints of a training run: the whole state as plain arrays plus JSON metadata.

``OUT/checkpoint/state.npz`` holds every leaf of the :class:`TrainingState` in tree order
(networks, optimisers, targets, normaliser, both replay buffers, key) and, as one JSON string, the
host loop's counters, its numpy generator and the config; ``meta.json`` repeats those for people and
tools. The state file is written atomically and carries its own metadata, so a kill leaves the
previous checkpoint or the new one whole. No pickle. :class:`Writer` writes in a background thread
while training goes on. In a distributed run every process takes part in gathering the state and
process 0 writes it; every process reads it back.
"""

from __future__ import annotations

import dataclasses
import json
import threading
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.agents.ddpg_bc.config import TrainConfig
from regrasp_mjx.agents.ddpg_bc.learner import TrainingState
from regrasp_mjx.core import distributed
from regrasp_mjx.core.atomic import atomic_write, dumps, write_json
from regrasp_mjx.core.config import ConfigError

# Learner fields added after checkpoints were first written; each default reproduces what those
# checkpoints ran, so a checkpoint without them resumes as if they had been saved.
ADDED_FIELDS = ("critic_layer_norm", "bc_decay_epochs", "bc_decay_to", "action_l2_decay", "shard")
META = "meta_json"  # the metadata's key in state.npz (checkpoints before it have meta.json alone)


def config_json(cfg: TrainConfig) -> dict[str, Any]:
    """``cfg`` as the JSON a checkpoint and an exported policy store (tuples become lists)."""
    return json.loads(dumps(dataclasses.asdict(cfg)))


def with_added_defaults(saved: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's config with the learner fields added since filled in at their defaults."""
    defaults = config_json(TrainConfig())
    return {**{k: defaults[k] for k in ADDED_FIELDS if k not in saved}, **saved}


def _like(template: Any, saved: np.ndarray) -> Any:
    """A restored leaf of the template's kind: Python scalars stay Python scalars and weakly typed
    scalars stay weak, so the resumed state traces exactly like a fresh one (no recompile)."""
    if not isinstance(template, jax.Array):
        return type(template)(saved.item()) if np.ndim(saved) == 0 else np.asarray(saved)
    if template.weak_type:
        return jnp.asarray(saved.item())
    return jnp.asarray(saved, dtype=template.dtype)


def _host_arrays(ts: TrainingState, meta: dict[str, Any]) -> dict[str, np.ndarray] | None:
    """What ``state.npz`` holds, copied off the devices now (process 0's; None on the others)."""
    leaves = distributed.to_host(jax.tree_util.tree_leaves(ts))
    if not distributed.is_main():
        return None
    # on the CPU backend a host view can share memory the next (donating) iteration reuses: copied
    # there; from a GPU the host arrays are fresh already (32 seeds' buffers are ~6 GB: no second copy)
    copy = jax.default_backend() == "cpu"
    arrays = {f"leaf_{i:05d}": np.array(x, copy=True) if copy else np.asarray(x) for i, x in enumerate(leaves)}
    arrays[META] = np.array(dumps(meta))
    return arrays


def _write(folder: Path, arrays: dict[str, np.ndarray]) -> None:
    atomic_write(folder / "state.npz", lambda f: np.savez(f, **arrays))
    write_json(folder / "meta.json", json.loads(str(arrays[META])), indent=None)


class Writer:
    """Checkpoints written in a background thread: :meth:`save` (a collective in a distributed run:
    every process calls it; process 0 writes) copies the state to the host at once
    (the next iteration reuses its device buffers) and returns; the file is written while training
    goes on (for 8 seeds, ~1.6 GB of replay buffers: ~5 s on the H100 host). One write at a time;
    :meth:`wait` joins it and raises what it raised."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def save(self, folder: Path, ts: TrainingState, meta: dict[str, Any]) -> None:
        self.wait()  # before the copy: one state on the host at a time (32 seeds' is ~6 GB)
        arrays = _host_arrays(ts, meta)  # a collective: every process
        if arrays is None:
            return
        self._thread = threading.Thread(target=self._run, args=(folder, arrays), name="checkpoint", daemon=False)
        self._thread.start()

    def _run(self, folder: Path, arrays: dict[str, np.ndarray]) -> None:
        try:
            _write(folder, arrays)
        except BaseException as err:  # raised in the training thread by wait()
            self._error = err

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            err, self._error = self._error, None
            raise err


def load(folder: Path, template: TrainingState, cfg: TrainConfig) -> tuple[TrainingState, dict[str, Any]]:
    """The state and metadata in ``folder``, shaped like ``template`` (host arrays; place them on the
    devices with :meth:`Learner.place`). Raises :class:`ConfigError` when there is no checkpoint, it
    was made with other settings (``epochs`` may grow), or its arrays do not match."""
    meta_path, state_path = folder / "meta.json", folder / "state.npz"
    if not (meta_path.is_file() and state_path.is_file()):
        raise ConfigError(f"--resume: no checkpoint in {folder}")
    try:
        with np.load(state_path, allow_pickle=False) as f:  # the state's own metadata is the truth
            meta = json.loads(str(f[META])) if META in f.files else json.loads(meta_path.read_text())
    except Exception as err:
        raise ConfigError(f"--resume: {state_path} is corrupt or unreadable: {err}") from err
    saved, now = with_added_defaults(meta["config"]), config_json(cfg)
    saved.pop("epochs", None)
    now.pop("epochs", None)
    if saved != now:
        diff = sorted(k for k in now if saved.get(k) != now[k])
        raise ConfigError(
            f"--resume: the checkpoint in {folder} was made with other settings ({diff}); "
            "resume with the same preset, exploration and overrides (epochs may grow)"
        )
    leaves, treedef = jax.tree_util.tree_flatten(template)
    try:
        with np.load(state_path, allow_pickle=False) as f:
            saved_leaves = [f[f"leaf_{i:05d}"] for i in range(len(leaves))]
            extra = len([k for k in f.files if k != META]) - len(leaves)
    except Exception as err:
        raise ConfigError(f"--resume: {state_path} is corrupt or unreadable: {err}") from err
    bad = [
        i
        for i, (a, b) in enumerate(zip(saved_leaves, leaves))
        if np.shape(a) != np.shape(b) or (isinstance(b, jax.Array) and a.dtype != b.dtype)
    ]
    if bad or extra:
        raise ConfigError(
            f"--resume: {state_path} does not match this run's networks and buffers "
            f"(array {bad[0] if bad else 'count'} differs)"
        )
    return jax.tree_util.tree_unflatten(treedef, [_like(t, x) for t, x in zip(leaves, saved_leaves)]), meta
