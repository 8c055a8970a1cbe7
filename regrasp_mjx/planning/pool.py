"""A pool of planner processes that never blocks its caller.

The learner submits failed (start, goal) problems and collects whatever has finished at its next
iteration; the demonstration builder uses the same pool. Each worker is a process with its own
pipe and one job at a time, so the parent always knows which job a worker holds: a job that
outlives ``timeout_s`` has its worker killed and replaced and is reported failed; a worker that
dies (a crash in native code, say) is replaced and its job reported failed; an exception inside a
plan is reported as that job's failure and the worker carries on. Workers exit by themselves if
their parent dies, so no process outlives the pool, and ignore Ctrl-C (SIGINT), which the parent
alone reports.

Workers are spawned (not forked, which JAX does not survive) and set ``JAX_PLATFORMS=cpu`` before
the planner's imports (this module imports JAX through ``host`` and ``scene``), so no worker takes
a GPU.
"""

from __future__ import annotations

import collections
import dataclasses
import multiprocessing as mp
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from regrasp_mjx.core.config import SceneConfig, is_integer, is_number, require
from regrasp_mjx.envs.host import HostChecker
from regrasp_mjx.planning.ompl_planner import OmplPlanner, PlannerConfig, straight_line
from regrasp_mjx.world.scene import load_scene

PlanFn = Callable[[dict[str, Any], dict[str, Any]], dict[str, Any]]


@dataclasses.dataclass
class JobResult:
    """What came back for one submitted problem.

    Attributes:
      job_id: the id :meth:`PlannerPool.submit` returned.
      ok: the worker returned a result (``result``); False when it raised, hung or died (``error``).
      result: the plan function's output (``solved``, ``plan_time_s``, ``poses``, ...).
      error: why the job failed.
      payload: what was submitted with the job, returned untouched (e.g. its problem index).
    """

    job_id: int
    ok: bool
    result: dict[str, Any] | None = None
    error: str = ""
    payload: Any = None


def plan_with_ompl(problem: dict[str, Any], options: dict[str, Any]) -> dict[str, Any]:
    """The default plan function: OMPL from ``problem['start']`` to ``problem['goal']``.

    ``options``: ``planner`` (a PlannerConfig as a dict), ``scene`` (a SceneConfig as a dict),
    ``seed``, ``clearance_mm`` (the collision margin, default 0) and ``method``: ``"ompl"``
    (default) or ``"straight_line"`` (the baseline). One
    planner per worker and options, built on first use. A problem that names its needle
    (``needle_radius``, ``wire_radius`` in metres) is planned around that one.
    """

    key = repr(sorted(options.items()))
    cache = plan_with_ompl.__dict__.setdefault("_planners", {})
    if key not in cache:
        scene = load_scene(SceneConfig(**options.get("scene", {})))
        cache[key] = OmplPlanner(
            PlannerConfig(**options.get("planner", {})),
            HostChecker(scene, options.get("clearance_mm", 0.0)),
            options.get("seed", 0),
        )
    planner = cache[key]
    base = cache.setdefault(("checker", key), planner.checker)  # the scene's own needle
    planner.checker = base.for_needle(problem.get("needle_radius"), problem.get("wire_radius"))
    if options.get("method", "ompl") == "straight_line":
        r = straight_line(planner.checker, problem["needle"], problem["start"], problem["goal"], planner.config)
    else:
        r = planner.plan(problem["needle"], problem["start"], problem["goal"])
    return {
        "solved": r.solved,
        "plan_time_s": r.plan_time_s,
        "poses": r.poses,
        "path_length_mm": r.path_length_mm,
        "error": r.error,
    }


def _worker_main(conn: Connection, parent_pid: int, plan_fn: PlanFn, options: dict[str, Any]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the parent reports it and stops the pool
    os.environ["JAX_PLATFORMS"] = "cpu"
    while True:
        if os.getppid() != parent_pid:  # orphaned: the parent died without closing us
            return
        if not conn.poll(0.5):
            continue
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        job_id, problem = msg
        try:
            conn.send((job_id, True, plan_fn(problem, options), ""))
        except Exception:  # the job failed, the worker lives on
            conn.send((job_id, False, None, traceback.format_exc(limit=3)))


@dataclasses.dataclass
class _Worker:
    process: mp.Process
    conn: Connection
    job: tuple[int, float] | None = None  # (job id, start time)


class PlannerPool:
    """Planner processes behind a bounded queue; :meth:`submit` and :meth:`collect` never block.

    Args:
      workers: number of planner processes.
      plan_fn: a top-level (picklable) function ``(problem, options) -> dict`` run in the workers.
      options: passed to every ``plan_fn`` call.
      queue_size: most jobs waiting for a worker; :meth:`submit` returns None beyond it.
      timeout_s: a job running longer has its worker killed and replaced, and is reported failed.
    """

    def __init__(
        self,
        workers: int,
        plan_fn: PlanFn = plan_with_ompl,
        options: dict[str, Any] | None = None,
        queue_size: int = 1024,
        timeout_s: float = 60.0,
    ):
        require(is_integer(workers) and workers >= 1, "workers", workers, "an integer >= 1")
        require(is_integer(queue_size) and queue_size >= 1, "queue_size", queue_size, "an integer >= 1")
        require(is_number(timeout_s) and timeout_s > 0, "timeout_s", timeout_s, "a finite number of seconds > 0")
        self._ctx = mp.get_context("spawn")
        self._plan_fn, self._options = plan_fn, dict(options or {})
        self.queue_size, self.timeout_s = queue_size, float(timeout_s)
        self._pending: collections.deque[tuple[int, dict[str, Any]]] = collections.deque()
        self._payloads: dict[int, Any] = {}
        self._done: list[JobResult] = []
        self._next_id = 0
        self._closed = False
        self.replaced = 0
        self._workers = [self._spawn() for _ in range(workers)]

    # ---- public -----------------------------------------------------------------------------
    def submit(self, problem: dict[str, np.ndarray], payload: Any = None) -> int | None:
        """Queues a problem (``needle``, ``start``, ``goal`` 7-vectors); None if the queue is full."""
        if self._closed:
            raise RuntimeError("the pool is closed")
        self._poll()
        if len(self._pending) >= self.queue_size:
            return None
        job_id = self._next_id
        self._next_id += 1
        self._pending.append((job_id, problem))
        self._payloads[job_id] = payload
        self._dispatch()
        return job_id

    def collect(self) -> list[JobResult]:
        """Everything finished since the last call (successes and failures); never waits."""
        self._poll()
        self._dispatch()
        out, self._done = self._done, []
        return out

    def wait(self, timeout_s: float) -> list[JobResult]:
        """Collects until every submitted job has come back or ``timeout_s`` passed."""
        deadline = time.monotonic() + timeout_s
        results = self.collect()
        while self.in_flight and time.monotonic() < deadline:
            time.sleep(0.01)
            results += self.collect()
        return results

    @property
    def in_flight(self) -> int:
        """Jobs queued or running."""
        return len(self._pending) + sum(w.job is not None for w in self._workers)

    def close(self) -> None:
        """Stops every worker (politely, then by force); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        for w in self._workers:
            try:
                w.conn.send(None)
            except (OSError, BrokenPipeError):
                pass
        deadline = time.monotonic() + 2.0
        for w in self._workers:
            w.process.join(max(0.0, deadline - time.monotonic()))
            if w.process.is_alive():
                w.process.kill()
                w.process.join(5.0)
            w.conn.close()

    def __enter__(self) -> PlannerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

    # ---- internals --------------------------------------------------------------------------
    def _spawn(self) -> _Worker:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(
            target=_worker_main, args=(child, os.getpid(), self._plan_fn, self._options), daemon=True
        )
        # Ctrl-C reaches every process of the terminal's group: the worker starts with it ignored (kept
        # across exec, and Python then installs no KeyboardInterrupt of its own), so only the parent reports
        ignoring = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if ignoring else None
        try:
            proc.start()
        finally:
            if ignoring:
                signal.signal(signal.SIGINT, previous)
        child.close()
        return _Worker(proc, parent)

    def _replace(self, i: int, error: str) -> None:
        w = self._workers[i]
        if w.job is not None:
            self._finish(w.job[0], False, None, error)
        if w.process.is_alive():
            w.process.kill()
        w.process.join(5.0)
        w.conn.close()
        self._workers[i] = self._spawn()
        self.replaced += 1

    def _finish(self, job_id: int, ok: bool, result: Any, error: str) -> None:
        self._done.append(JobResult(job_id, ok, result, error, self._payloads.pop(job_id, None)))

    def _poll(self) -> None:
        now = time.monotonic()
        for i, w in enumerate(self._workers):
            try:
                while w.conn.poll():
                    job_id, ok, result, error = w.conn.recv()
                    self._finish(job_id, ok, result, error)
                    w.job = None
            except (EOFError, OSError):
                self._replace(i, f"worker died (exit code {w.process.exitcode})")
                continue
            if not w.process.is_alive():
                self._replace(i, f"worker died (exit code {w.process.exitcode})")
            elif w.job is not None and now - w.job[1] > self.timeout_s:
                self._replace(i, f"timed out after {self.timeout_s:g} s; worker replaced")

    def _dispatch(self) -> None:
        for w in self._workers:
            if w.job is None and self._pending:
                job_id, problem = self._pending.popleft()
                try:
                    w.conn.send((job_id, problem))
                    w.job = (job_id, time.monotonic())
                except (OSError, BrokenPipeError):
                    self._pending.appendleft((job_id, problem))


def plan_all(episodes: Any, rows: list[int], options: dict[str, Any], workers: int, budget_s: float) -> dict:
    """Problems ``rows`` of ``episodes`` (a ``sampling.Episode`` batch) each planned once by
    ``workers`` processes of :func:`plan_with_ompl` (``options``; a plan that outlives three budgets
    and a minute is stopped): ``{row: result}``, ``None`` where the job failed."""
    with PlannerPool(workers, options=options, timeout_s=3 * budget_s + 60, queue_size=max(1, len(rows))) as pool:
        for i in rows:
            pool.submit(episodes.problem(i), payload=i)
        return {r.payload: r.result if r.ok else None for r in pool.wait(24 * 3600)}


def summarize_plans(results: list[dict | None], budget_s: float) -> dict[str, Any]:
    """Table II's numbers of one planner over its problems' results (:func:`plan_all`'s values):
    success rate; planning time mean and median over the solved ones, and the mean over all with a
    failed job counted at three budgets; path length over the solved ones [mm]."""
    solved = [r for r in results if r is not None and r["solved"]]
    times = np.array([r["plan_time_s"] for r in solved])
    every = np.array([3 * budget_s if r is None else r["plan_time_s"] for r in results])
    return {
        "problems": len(results),
        "success_rate": len(solved) / max(1, len(results)),
        "plan_time_mean_s": float(times.mean()) if solved else None,
        "plan_time_median_s": float(np.median(times)) if solved else None,
        "plan_time_mean_all_s": float(every.mean()) if len(every) else None,
        "path_length_mm": float(np.mean([r["path_length_mm"] for r in solved])) if solved else None,
    }
