"""What runs on the Ray cluster for :mod:`regrasp_mjx.core.jobs`: one job's task (:func:`run_task`: its
process, run to the end; the job's arguments made when the task starts, so a task run again after its node
died resumes) and the :class:`Board` actor the jobs of one call wait on (compiled programs, started jobs).
The driver's side (which jobs to run, their resources, the progress lines) is in :mod:`regrasp_mjx.core.jobs`."""

from __future__ import annotations

import asyncio
import ctypes
import dataclasses
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import ray

RETRIES = 3  # times Ray runs a job's task again after its node or worker died


class JobFailed(Exception):
    """A job's process ended without its finish file (``code``: its exit status)."""

    def __init__(self, name: str, code: int | str | None, wall_s: float, why: str):
        super().__init__(name, code, wall_s, why)
        self.name, self.code, self.wall_s, self.why = name, code, wall_s, why


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    job: Any  # regrasp_mjx.core.jobs.Job
    fraction: float | None
    cpu_only: bool
    omp_threads: str | None = None  # the driver's OMP_NUM_THREADS (None: unset)


@ray.remote(num_cpus=0)
class Board:
    """What the jobs of one call wait for: which ``programs`` keys are compiled, which jobs have
    started or ended; and the events the driver prints (started, compiled, spared)."""

    def __init__(self, opened: list[str]):
        self.opened_keys, self.begun, self.events = set(opened), set(), []
        self.changed = asyncio.Condition()

    async def _wait(self, ready) -> None:
        async with self.changed:
            await self.changed.wait_for(ready)

    async def _note(self, event=None) -> None:
        async with self.changed:
            if event is not None:
                self.events.append(event)
            self.changed.notify_all()

    async def opened(self, key: str) -> bool:
        await self._wait(lambda: key in self.opened_keys)
        return True

    async def started(self, names: list[str]) -> bool:
        await self._wait(lambda: all(n in self.begun for n in names))
        return True

    async def any_to_start(self, names: list[str]) -> bool:
        return not all(n in self.begun for n in names)

    async def start(self, name: str, where: str) -> None:
        self.begun.add(name)
        await self._note(("started", name, where))

    async def compiled(self, name: str, key: str) -> None:
        if key not in self.opened_keys:
            self.opened_keys.add(key)
            await self._note(("compiled", name, ""))

    async def spared(self, name: str) -> None:
        self.begun.add(name)
        await self._note(("spared", name, ""))

    async def ended(self, name: str, key: str | None) -> None:
        self.begun.add(name)  # a job that ended, run or not, is no longer to start
        if key:
            self.opened_keys.add(key)
        await self._note()

    async def take(self) -> list[tuple[str, str, str]]:
        events, self.events = self.events, []
        return events


# a rerun whose folder's lock outlives its dead node (a lock on NFS is freed by the server's lease, not at
# once) waits for it: every LOCK_WAIT_S until LOCK_PATIENCE_S, then fails as any job does
IN_USE = "is in use by another run"
LOCK_WAIT_S, LOCK_PATIENCE_S = 5.0, 300.0


@ray.remote(max_retries=RETRIES)
def run_task(spec: TaskSpec, board, *_waits) -> dict | None:
    """One job's task: runs its process to the end (the job's arguments made now, so a task run
    again resumes) and returns ``{"wall_s", "node"}``; raises :class:`JobFailed` when it ends
    without its finish file. Returns None (a helper not needed any more) or at once (finished).

    It never waits on Ray (``ray.get``) once it runs: a task blocked there gives its CPUs back to
    Ray, which would start another job on them (a helper's one question comes first, on GPUs)."""
    job = spec.job
    node = ray.get_runtime_context().get_node_id()[:8]
    if job.done():  # run again after its job had finished (its node died after the finish file was written)
        return {"wall_s": 0.0, "node": node}
    if job.helps and not ray.get(board.any_to_start.remote(list(job.helps))):
        ray.get(board.spared.remote(job.name))  # before it returns (nothing runs: blocking costs nothing)
        return None
    env, where = _environment(spec, node)
    job.log.parent.mkdir(parents=True, exist_ok=True)
    board.start.remote(job.name, where)
    t0 = time.perf_counter()
    while True:
        code, offset = _run_process(job, env, where, board)
        if code == 0 or time.perf_counter() - t0 > LOCK_PATIENCE_S or not _printed(job.log, offset, IN_USE):
            break
        time.sleep(LOCK_WAIT_S)  # a lock left by this job's dead node: started again once it is freed
    wall = time.perf_counter() - t0
    if code == 0 and job.done():
        return {"wall_s": wall, "node": node}
    why = f"exit {code}" if code != 0 else f"exit 0 without {job.finished.name}"
    raise JobFailed(job.name, code, wall, why)


def _environment(spec: TaskSpec, node: str) -> tuple[dict[str, str], str]:
    """The job process's environment, and where it runs (for its log and the progress line)."""
    env = dict(os.environ)
    if spec.omp_threads is None:  # Ray sets OMP_NUM_THREADS to a task's CPUs (1 for a GPU job's 0): not ours
        env.pop("OMP_NUM_THREADS", None)
    else:
        env["OMP_NUM_THREADS"] = spec.omp_threads
    if spec.cpu_only:
        env["JAX_PLATFORMS"] = "cpu"  # Ray gave it no GPU: said explicitly (ray#49147)
        return env, f"node {node}, its CPUs"
    gpu_ids = ",".join(str(g) for g in ray.get_gpu_ids())
    # one spelling only: with both XLA_CLIENT_MEM_FRACTION and the older XLA_PYTHON_CLIENT_MEM_FRACTION
    # set, the CUDA plugin fails to start and JAX runs on the CPU (seen on the H200, jaxlib 0.11, where the
    # older one is read; regrasp_mjx.core.gpu_memory reads it too)
    env.pop("XLA_CLIENT_MEM_FRACTION", None)
    env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{spec.fraction:.3f}"
    return env, f"node {node}, GPU {gpu_ids}, {spec.fraction:.0%} of its memory"


def _run_process(job, env: dict[str, str], where: str, board) -> tuple[int, int]:
    """Runs the job's process once to its end, its output appended to its log after a line naming
    where and what; tells the board when its log shows ``job.compiled``. Returns its exit code and
    where its output begins in the log."""
    argv = job.argv()  # made now: a job started again after its node died resumes (e.g. --resume)
    with open(job.log, "a") as out:
        out.write(f"\n# {time.strftime('%Y-%m-%d %H:%M:%S')} started on {where}: python {shlex.join(argv)}\n")
        out.flush()
        offset = out.tell()
        parent = os.getpid()
        proc = subprocess.Popen(
            [sys.executable, *argv],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
            preexec_fn=lambda: _die_with_parent(parent),
        )
        try:
            seen = not (job.programs and job.compiled)
            while proc.poll() is None:
                time.sleep(0.5)
                if not seen and _printed(job.log, offset, job.compiled):
                    seen = True
                    board.compiled.remote(job.name, job.programs)
        finally:
            if proc.poll() is None:  # the task was cancelled: its process goes with it
                proc.terminate()
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
    return proc.returncode, offset


def _printed(log: Path, offset: int, text: str) -> bool:
    """Whether the log since ``offset`` (where this start's output begins) holds ``text``."""
    try:
        with open(log, "rb") as f:
            f.seek(offset)
            return text in f.read().decode(errors="replace")
    except OSError:
        return False


# looked up before any fork: the child runs as little Python as it can before exec
_PRCTL = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None
_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    """In the job's process before it runs: SIGTERM it when the task's worker dies (a cancelled
    task, a node that dies), so no job runs on without its task (Linux; elsewhere nothing); a worker
    that died before this was set leaves the process an orphan already: it ends at once."""
    if _PRCTL is not None:
        _PRCTL(_PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent:
            os._exit(1)
