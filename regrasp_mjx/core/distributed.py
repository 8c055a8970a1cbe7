"""Several processes (hosts) training one program, on JAX's own distributed runtime.

Every process runs the same host loop and the same jitted programs over one global mesh of all
processes' devices (``jax.devices()``). What runs where:

- the device work (rollouts, updates, evaluation) is one SPMD program over the global mesh;
- values the host reads (outcomes, metrics, evaluations, parameters to export or checkpoint) are
  gathered from every process (:func:`to_host`, a collective all processes call);
- the planner pool runs on process 0 only; the demonstrations it returns are broadcast
  (:func:`broadcast`) so every process inserts the same ones;
- logs, TensorBoard, checkpoints, exported policies and the final evaluation are process 0's
  (:func:`is_main`); a resumed run reads the checkpoint on every process (a shared file system).

On a single process every helper is the identity (or ``np.asarray``), so nothing changes there.
CPU devices exchange data through gloo (JAX has no other CPU collectives across processes).
"""

from __future__ import annotations

import itertools
from typing import Any

import jax
import numpy as np
from jax._src import distributed as jax_distributed  # the coordination service's client: no public handle
from jax.experimental import multihost_utils

from regrasp_mjx.core.config import ConfigError

MEET_TIMEOUT_S = 600.0
_MEETINGS = itertools.count()  # every process calls the collectives in the same order: the same ids


def initialize(coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None) -> None:
    """Joins this process to a distributed run: ``jax.distributed.initialize`` with the given
    coordinator (``HOST:PORT``), process count and index, or, left out, what JAX detects (SLURM,
    Open MPI, ``JAX_COORDINATOR_ADDRESS``). Must run before anything else touches a device."""
    # Cross-process collectives between CPU devices need gloo; GPU devices use NCCL regardless.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)
    except ValueError as err:  # nothing given and nothing detected, say
        raise ConfigError(
            f"--distributed: JAX could not join a run ({err}); accepted: --coordinator HOST:PORT --num-processes N "
            "--process-id I, or a cluster JAX detects (SLURM, Open MPI, JAX_COORDINATOR_ADDRESS)"
        ) from None


def options_problem(
    distributed: bool, coordinator: str | None, num_processes: int | None, process_id: int | None
) -> str | None:
    """Why the command line's ``--distributed``, ``--coordinator``, ``--num-processes`` and
    ``--process-id`` cannot start a run (None when they can), checked before any work: the
    coordinator is ``HOST:PORT``; the count and index are given together, ``0 <= index < count``,
    and only to join a run (with ``--coordinator``, or ``--distributed`` where the coordinator is
    detected: SLURM, Open MPI, ``JAX_COORDINATOR_ADDRESS``)."""
    if coordinator is not None:
        host, _, port = coordinator.rpartition(":")
        if not host.strip() or not port.isdigit() or not 1 <= int(port) <= 65535:
            return f"--coordinator {coordinator} is not accepted: HOST:PORT, e.g. node0:12345 (process 0's address)"
    if (num_processes is None) != (process_id is None):
        return "--num-processes and --process-id are accepted only together: the run's process count and this index"
    if num_processes is None:
        return None
    if not (coordinator or distributed):
        return (
            f"--num-processes {num_processes} --process-id {process_id} is not accepted without --coordinator "
            "HOST:PORT (or --distributed with the coordinator detected): a single-process run would ignore them"
        )
    if num_processes < 1 or not 0 <= process_id < num_processes:
        return (
            f"--num-processes {num_processes} --process-id {process_id} is not accepted: a count >= 1 and an "
            f"index in [0, {max(num_processes, 1)})"
        )
    return None


def is_main() -> bool:
    """Whether this process writes files and talks to the planners (process 0)."""
    return jax.process_index() == 0


def multi_process() -> bool:
    return jax.process_count() > 1


def to_host(tree: Any) -> Any:
    """The whole value of every leaf as numpy on this process. Leaves spread over other processes'
    devices are all-gathered: every process must call this at the same point with the same tree."""

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree.map(one, tree)


def broadcast(tree: Any) -> Any:
    """Process 0's value of ``tree`` (numpy leaves of the same shapes on every process) on all."""
    if not multi_process():
        return tree
    _meet()
    return jax.tree.map(np.asarray, multihost_utils.broadcast_one_to_all(tree))


def _meet() -> None:
    """Waits (up to ``MEET_TIMEOUT_S``) on the coordination service until every process is here.
    A collective's gloo context gives up when a peer comes 30 s late, and process 0 does work the
    others do not (the planners, the run's files) before it broadcasts: a CI run lost a broadcast so."""
    jax_distributed.global_state.client.wait_at_barrier(f"regrasp_mjx_{next(_MEETINGS)}", int(1e3 * MEET_TIMEOUT_S))


def sync(name: str) -> None:
    """Waits until every process reaches the barrier ``name``."""
    if multi_process():
        multihost_utils.sync_global_devices(name)
