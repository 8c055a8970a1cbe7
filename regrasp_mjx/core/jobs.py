"""Command-line jobs run as Ray tasks: what ``sweep`` and ``recipe`` run (on :mod:`regrasp_mjx.core.cluster`).

A job is one process (``python -m regrasp_mjx.train ...``) with the jobs it needs, the share of one
GPU's memory it takes and the file that says it has finished. :func:`run_jobs` submits each job not
finished yet as one Ray task that runs the process and waits for it; Ray places it where its share
fits, several side by side on one GPU where their shares allow, and never starts one whose need
failed (the needs are the task's arguments). A job's task asks for ``num_gpus`` = its share scaled
to the cluster's smallest GPU (a share of 1 or more is a whole GPU) plus a CUDA context; the process
is given that fraction of the GPU's memory (``XLA_PYTHON_CLIENT_MEM_FRACTION``), as Ray's fractions are only
counted, not enforced. Without GPUs a job takes the CPUs of the cluster's largest node (one job at a time
on a node of that size; a smaller node runs none: :func:`resources`) and its process is told to use the
CPU (``JAX_PLATFORMS=cpu``). A job's task runs ``Job.cpus`` CPU cores beside it.

A job that asks for more than any live node has is refused before anything runs (Ray would keep it
waiting, silently: its warning is not passed on). While jobs wait and none runs (Ray cannot place
them now: a busy cluster, or the node that could died), a line every ``heartbeat_s`` says which wait,
for what, and what the cluster has free; they wait on, as a busy cluster frees its resources in time.

Resume rules: a job whose finish file exists is skipped, and so is one whose dependents have all
finished, so a killed schedule started again runs only what is left; each job resumes its own work
as its command does (its arguments are made when its task starts, ``Job.argv``). A node that dies
takes its tasks with it: Ray runs them again on another node (:data:`regrasp_mjx.core.job_task.RETRIES`), where they resume
from their last checkpoint; a task started again after its job finished returns at once.

Jobs that compile the same programs (``Job.programs``, e.g. one student variant's seeds) wait until
the first of them in the list has compiled (its log shows ``Job.compiled``, or it ends): they then
load the programs from the persistent compilation cache the commands share
(:func:`regrasp_mjx.core.xla_flags.cache_folder`) instead of compiling them side by side, which on
the GPU machine's CPU cores took several minutes for six students at once. A key one of whose jobs
finished in an earlier call counts as compiled (the cache is kept on the same machine).

A job that ``helps`` others runs only to save them time (a recipe's precompile jobs compile their
programs ahead, on an untrained network of their shape, while the teachers train): it runs only
while a job it helps is still to start, none waits for it to finish, and its failure fails nothing
(those jobs compile their own programs). It yields to the jobs that do the work: it starts only
after every job that becomes ready with it has started.

The gates (compiled programs, started jobs) are one small Ray actor per call (:class:`regrasp_mjx.core.job_task.Board`).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from regrasp_mjx.core import host_loop
from regrasp_mjx.core.cluster import Cluster, amount, check_fits, resources_now
from regrasp_mjx.core.job_task import Board, JobFailed, TaskSpec, run_task

HEARTBEAT_S = 60.0  # how often the running jobs' last log lines (or, none running, what the rest wait for) are shown
# of a GPU's memory each process takes outside its share (its CUDA context and libraries, about 0.5 GB
# on an 80 GB H100): fifteen processes whose shares summed to 0.9 ran out of memory starting
CONTEXT_SHARE = 0.01
MAX_FRACTION = 0.95  # of a GPU's memory one process may take (XLA's own default is 0.75)


@dataclasses.dataclass(frozen=True)
class Job:
    """One process. ``argv`` makes its ``python -m ...`` arguments when it starts (so a restart
    can add ``--resume``); ``finished`` exists once it has finished; ``needs`` names jobs that must
    finish first; ``share`` is the fraction of an 80 GB GPU's memory it may take (scaled to the
    GPU it runs on, module docstring); ``stage`` groups jobs for the progress lines; its output goes
    to ``log``; jobs of one ``programs`` key wait for the first to print ``compiled`` (see the
    module's docstring); ``helps`` names the jobs it only saves time for (its failure fails
    nothing); ``cpus``: the CPU cores it keeps busy beside its GPU share (a planner's workers)."""

    name: str
    stage: str
    argv: Callable[[], list[str]]
    finished: Path
    log: Path
    share: float = 1.0
    needs: tuple[str, ...] = ()
    programs: str | None = None
    compiled: str | None = None
    helps: tuple[str, ...] = ()
    cpus: int = 0

    def done(self) -> bool:
        return self.finished.is_file()


class JobsStopped(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped the running jobs (they resume when started again)."""


def last_line(path: Path, size: int = 4096) -> str:
    """The last non-empty line of a log (progress bars write ``\\r``-separated updates)."""
    try:
        with open(path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - size))
            tail = f.read().decode(errors="replace")
    except OSError:
        return ""
    parts = [p.strip() for p in tail.replace("\r", "\n").splitlines() if p.strip()]
    return parts[-1][:160] if parts else ""


def resources(job: Job, cluster: Cluster) -> dict[str, float]:
    """The Ray resources a job's task asks for (module docstring).

    Without GPUs a job asks for every CPU of the cluster's largest node, as XLA on the CPU (and a
    planner's workers) use every core the process sees: two jobs on one node would each believe
    they had it all and slow each other down (a job asking for the smallest node's CPUs let a
    large node run several at once beside a small head node). Ray cannot ask for "a whole node,
    whichever": a custom resource per node needs every node started by us, node affinity ties a
    job to one node (not run again elsewhere when it dies), and XLA:CPU sizes its threads by the
    cores the process may run on, not by a number we could pass. So a node smaller than the
    largest runs no job: a CPU cluster is best of nodes of one size (or with its head at
    ``--num-cpus 0``)."""
    if not cluster.gpus:
        return {"num_cpus": max(cluster.most_cpus, 1), "num_gpus": 0}
    if job.share >= 1.0:
        gpu = 1.0
    else:  # Ray counts fractions in steps of 1e-4: rounded up, so shares that fit do not overfill
        gpu = min(1.0, -(-(job.share + CONTEXT_SHARE) * cluster.scale * 1e4 // 1) / 1e4)
    return {"num_cpus": min(job.cpus, cluster.node_cpus), "num_gpus": gpu}


def memory_fraction(job: Job, cluster: Cluster) -> float | None:
    """The fraction of its GPU's memory a job's process is given; None without GPUs."""
    if not cluster.gpus:
        return None
    return MAX_FRACTION if job.share >= 1.0 else min(job.share * cluster.scale, MAX_FRACTION)


def run_jobs(
    jobs: list[Job],
    cluster: Cluster,
    log: Callable[[str], None],
    heartbeat_s: float = HEARTBEAT_S,
    on_end: Callable[[dict[str, dict]], None] | None = None,
) -> dict[str, dict]:
    """Runs the jobs not finished yet on ``cluster`` (see the module's docstring); returns, per job
    this call started, ``{"exit": code, "wall_s": seconds, "stage": stage, "node": node}`` (exit
    None: not started because a job it needs failed; "stopped": running when this call was
    stopped; "lost": its task lost, its node died more often than Ray runs it again), and passes the same record to ``on_end`` each time a job ends. A SIGTERM or Ctrl-C
    cancels the jobs (their processes are stopped) and raises :class:`JobsStopped`; they resume when
    started again."""
    by_name = {j.name: j for j in jobs}
    for j in jobs:
        unknown = [n for n in j.needs + j.helps if n not in by_name]
        if unknown:
            raise ValueError(f"job {j.name} needs unknown jobs {unknown}")
    todo = _needs_first(_needed(jobs))  # a job after its needs: its task takes theirs as arguments
    spared = sum(1 for j in jobs if j not in todo and not j.done())
    finished_before = len(jobs) - len(todo) - spared
    log(
        f"{len(jobs)} jobs: {finished_before} finished already, "
        + (f"{spared} no longer needed (what needs them has finished), " if spared else "")
        + f"{len(todo)} to run on {cluster.describe()}"
    )
    if not todo:
        return {}
    asks = {j.name: resources(j, cluster) for j in todo}
    check_fits(asks)
    opened = {j.programs for j in jobs if j.programs and j.done()}  # compiled by a finished job: in the cache
    # on this process's node: the board must outlive any other node (a dead node's jobs run again elsewhere)
    here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
    board = Board.options(scheduling_strategy=here).remote(sorted(opened))
    refs = _submit(todo, cluster, board, asks)
    schedule = _Schedule(todo, refs, board, log, heartbeat_s, on_end, asks)
    # SIGTERM takes Ctrl-C's way out (the jobs are cancelled, then the command ends) through Ctrl-C's own
    # handler: one that lands in a garbage-collector callback or a __del__, where Python would drop the
    # KeyboardInterrupt and the command go on, is raised again a moment later (as a SIGINT)
    previous = signal.signal(signal.SIGTERM, host_loop._on_sigint) if _main_thread() else None
    try:
        return schedule.follow()
    except KeyboardInterrupt as err:
        stopped = schedule.stop()
        raise JobsStopped(
            f"stopped {len(stopped)} running job(s)" + (f" ({', '.join(stopped)})" if stopped else "")
        ) from err
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        ray.kill(board)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _opener(todo: list[Job], key: str) -> Job | None:
    """The job of a ``programs`` key that compiles them: the first in the list not finished (the
    others wait for it)."""
    return next((j for j in todo if j.programs == key), None)


def _submit(todo: list[Job], cluster: Cluster, board, asks: dict[str, dict[str, float]]) -> dict[str, ray.ObjectRef]:
    """Each job's task, its needs' tasks (and for a job that waits, the board's gates) as its arguments."""
    refs: dict[str, ray.ObjectRef] = {}
    for job in todo:
        waits = [refs[n] for n in job.needs if n in refs]
        if job.programs and _opener(todo, job.programs) is not job:
            waits.append(board.opened.remote(job.programs))
        if job.helps:  # helpers start after the work that becomes ready with them has started
            peers = [p.name for p in todo if not p.helps and set(p.needs) <= set(job.needs)]
            waits.append(board.started.remote(peers))
        spec = TaskSpec(job, memory_fraction(job, cluster), not cluster.gpus, os.environ.get("OMP_NUM_THREADS"))
        refs[job.name] = run_task.options(**asks[job.name]).remote(spec, board, *waits)
    return refs


def _needs_first(todo: list[Job]) -> list[Job]:
    """The jobs in list order, except that a job comes after the jobs it needs (its task takes theirs
    as arguments); jobs that need each other are refused."""
    names, placed, out = {j.name for j in todo}, set(), []
    left = list(todo)
    while left:
        ready = [j for j in left if all(n in placed or n not in names for n in j.needs)]
        if not ready:
            raise ValueError(f"jobs {[j.name for j in left]} need each other: no order runs them")
        for j in ready:
            placed.add(j.name)
            out.append(j)
        left = [j for j in left if j.name not in placed]
    return out


class _Schedule:
    """The driver's view of one call: which jobs started (from the board), ended (from their
    tasks), and the progress lines."""

    def __init__(self, todo, refs, board, log, heartbeat_s, on_end, asks):
        self.refs, self.board, self.log, self.heartbeat_s, self.on_end = refs, board, log, heartbeat_s, on_end
        self.asks = asks
        self.jobs = {j.name: j for j in todo}
        self.order = {j.name: i for i, j in enumerate(todo)}  # needs before their dependents
        self.pending = {ref: name for name, ref in refs.items()}
        self.began: set[str] = set()  # jobs whose task has started their process
        self.ended: set[str] = set()
        self.running: dict[str, float] = {}  # name -> when it started (this process's clock)
        self.out: dict[str, dict] = {}
        self.failed: set[str] = set()
        self.stage_left: dict[str, int] = {}
        for j in todo:
            self.stage_left[j.stage] = self.stage_left.get(j.stage, 0) + 1
        self.stage_t0: dict[str, float] = {}
        self.t0 = time.perf_counter()

    def follow(self) -> dict[str, dict]:
        last_beat = idle_since = time.perf_counter()
        while self.pending:
            ready, _ = ray.wait(list(self.pending), num_returns=len(self.pending), timeout=0.5)
            self._events()
            for ref in sorted(ready, key=lambda r: self.order[self.pending[r]]):
                self._ended(self.pending.pop(ref), ref)
            now = time.perf_counter()
            if self.running:
                idle_since = now
            if self.running and now - last_beat >= self.heartbeat_s:
                last_beat = now
                for name, t in self.running.items():
                    self.log(f"  {name} ({(now - t) / 60:.1f} min): {last_line(self.jobs[name].log) or '...'}")
            elif self.pending and min(now - last_beat, now - idle_since) >= self.heartbeat_s:
                last_beat = now  # none runs: say what the rest wait for, every heartbeat, as long as they wait
                self.log(self._waiting(now - idle_since))
        self._events()  # what the board heard after the last task ended
        return self.out

    def _waiting(self, idle_s: float) -> str:
        """Which jobs wait for Ray to place them, for what, and what the cluster has now."""
        names = sorted(self.pending.values(), key=self.order.__getitem__)
        ready = [n for n in names if all(d not in self.refs or d in self.ended for d in self.jobs[n].needs)]
        asks = [f"{n} ({amount(self.asks[n]['num_cpus'], self.asks[n]['num_gpus'])})" for n in ready]
        shown = ", ".join(asks[:6]) + (f" and {len(asks) - 6} more" if len(asks) > 6 else "")
        after = len(names) - len(ready)
        return (
            f"no job running for {idle_s / 60:.1f} min: waiting for Ray to place {shown or 'none'}"
            + (f" ({after} more wait for the jobs they need)" if after else "")
            + f"; the cluster now: {resources_now()}"
        )

    def _events(self) -> None:
        for kind, name, where in ray.get(self.board.take.remote()):
            job = self.jobs[name]
            if kind == "started" and name not in self.ended:  # a task's start can reach the board after its end
                self.began.add(name)
                self.running[name] = time.perf_counter()
                self.stage_t0.setdefault(job.stage, time.perf_counter())
                self.log(f"started {name} on {where}")
            elif kind == "compiled":
                self.log(f"{name} has compiled its programs: the jobs that share them start")
            elif kind == "spared":
                self.log(f"{name} not started: the jobs it helps have started")

    def _ended(self, name: str, ref) -> None:
        job, now = self.jobs[name], time.perf_counter()
        self.board.ended.remote(name, job.programs)  # a job that dies unseen still opens its gate
        self._events()  # its start first, where the board has it by now
        self.ended.add(name)
        try:
            result = ray.get(ref)
        except ray.exceptions.RayTaskError as err:
            result = err.cause if isinstance(err.cause, JobFailed) else JobFailed(name, None, 0.0, str(err))
        except ray.exceptions.RayError as err:  # the task was lost (its node died RETRIES times over)
            result = JobFailed(name, "lost", 0.0, f"{type(err).__name__}: {err}")
        started = self.running.pop(name, None)
        if result is None:  # a helper not needed any more
            self._stage_end(job, now)
            return
        need_failed = any(n in self.failed for n in job.needs)
        if isinstance(result, JobFailed) and need_failed and name not in self.began:  # its task never ran
            self.failed.add(name)
            self.out[name] = {"exit": None, "wall_s": 0.0, "stage": job.stage, "node": None}
            self.log(f"{name} not started: a job it needs failed")
        elif isinstance(result, JobFailed):
            self.failed.add(name)
            wall = result.wall_s or (now - started if started else 0.0)
            self.out[name] = {"exit": result.code, "wall_s": wall, "stage": job.stage, "node": None}
            verdict = f"FAILED ({result.why}; its output: {job.log})"
            if job.helps:
                verdict += "; the jobs it helps compile their own programs"
            self._line(name, verdict, wall, now)
        else:
            self.out[name] = {"exit": 0, "wall_s": result["wall_s"], "stage": job.stage, "node": result["node"]}
            self._line(name, "finished", result["wall_s"], now)
        self._stage_end(job, now)
        if self.on_end is not None:
            self.on_end(self.out)

    def _line(self, name: str, verdict: str, wall: float, now: float) -> None:
        done, left = len(self.out), len(self.pending)
        self.log(f"{name} {verdict} after {wall:.0f} s; {done} done, {left} left, {(now - self.t0) / 60:.1f} min in")

    def _stage_end(self, job: Job, now: float) -> None:
        self.stage_left[job.stage] -= 1
        if self.stage_left[job.stage] == 0 and job.stage in self.stage_t0:
            self.log(f"stage {job.stage}: {now - self.stage_t0[job.stage]:.0f} s")

    def stop(self) -> list[str]:
        """Cancels every task not ended (a running one's worker is killed, and its process with it:
        :func:`_die_with_parent`); records the running ones as stopped; returns their names."""
        for ref in self.pending:
            ray.cancel(ref, force=True)
        if self.pending:  # their workers gone, and with them their processes and folder locks
            ray.wait(list(self.pending), num_returns=len(self.pending), timeout=30)
        now = time.perf_counter()
        stopped = sorted(self.running)
        for name in stopped:
            job = self.jobs[name]
            self.out[name] = {"exit": "stopped", "wall_s": now - self.running[name], "stage": job.stage, "node": None}
        if stopped and self.on_end is not None:
            self.on_end(self.out)
        return stopped


def _needed(jobs: list[Job]) -> list[Job]:
    """The unfinished jobs that something still needs: every unfinished job that no other job needs
    (an end of the schedule), and the unfinished needs of a needed job (a job whose every dependent
    has finished, e.g. demonstrations deleted after training, is not run again); a job that helps
    others counts them as its dependents."""
    by_name = {j.name: j for j in jobs}
    dependents = {j.name: [d for d in jobs if j.name in d.needs] + [by_name[h] for h in j.helps] for j in jobs}
    memo: dict[str, bool] = {}

    def needed(j: Job) -> bool:
        if j.name not in memo:
            deps = dependents[j.name]
            memo[j.name] = not j.done() and (not deps or any(needed(d) for d in deps))
        return memo[j.name]

    return [j for j in jobs if needed(j)]
