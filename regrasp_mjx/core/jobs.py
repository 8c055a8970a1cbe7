"""Command-line jobs scheduled over the local GPUs: what ``sweep`` and ``recipe`` run.

A job is one process (``python -m regrasp_mjx.train ...``) with the jobs it needs, the share of one
GPU's memory it takes and the file that says it has finished. :func:`run_jobs` starts every job
whose needs have finished on the least-loaded GPU where its share still fits (several side by side
on one GPU where memory allows, ``XLA_PYTHON_CLIENT_MEM_FRACTION`` set to the share), one at a time
on a machine without a GPU, and never starts a job whose need failed. A job whose finish file exists
is skipped, and so is one whose dependents have all finished, so a killed schedule started again
runs only what is left; each job resumes its own work
as its command does (its arguments are made when it starts, ``Job.argv``).

Jobs that compile the same programs (``Job.programs``, e.g. one student variant's seeds) start one
at a time until one of them has compiled (its log shows ``Job.compiled``, or it ends): the others
then load the programs from the persistent compilation cache the commands share
(:func:`regrasp_mjx.core.xla_flags.cache_folder`) instead of compiling them side by side, which
on the GPU machine's CPU cores took several minutes for six students at once. A key one of whose
jobs finished in an earlier call counts as compiled (the cache is kept on the same machine).

A job that ``helps`` others runs only to save them time (a recipe's precompile jobs compile their
programs ahead, on an untrained network of their shape, while the teachers train): it is run only
while a job it helps is still to start, none waits for it to finish, and its failure fails nothing
(those jobs compile their own programs). It yields to the jobs that do the work: each pass places
those first, and no helper starts while one of them is ready and waits for GPU memory.

A share is of an 80 GB GPU's memory (:data:`REFERENCE_MIB`, the H100 the recipes were sized on), so
a job takes the same bytes on any GPU: on a 141 GB H200 its fraction is 0.57 of the share, and
more jobs fit side by side (measured as fractions, the recipe's helpers held 65 % of an H200 while
two selection candidates ran at a time, 2026-11-28). A share of 1 (a sweep's point) is a whole GPU
of any size.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from regrasp_mjx.core.config import ConfigError

HEARTBEAT_S = 60.0  # how often the running jobs' last log lines are shown
# of a GPU's memory each process takes outside its share (its CUDA context and libraries, about 0.5 GB
# on an 80 GB H100): fifteen processes whose shares summed to 0.9 ran out of memory starting
CONTEXT_SHARE = 0.01
# the memory the shares are of: an 80 GB H100 as nvidia-smi reports it [MiB]
REFERENCE_MIB = 81_559.0


@dataclasses.dataclass(frozen=True)
class Job:
    """One process. ``argv`` makes its ``python -m ...`` arguments when it starts (so a restart
    can add ``--resume``); ``finished`` exists once it has finished; ``needs`` names jobs that must
    finish first; ``share`` is the fraction of an 80 GB GPU's memory it may take (scaled to the
    GPU it runs on, module docstring); ``stage`` groups jobs
    for the progress lines; its output goes to ``log``; jobs of one ``programs`` key wait for one of
    them to print ``compiled`` (see the module's docstring); ``helps`` names the jobs it only saves
    time for (its failure fails nothing)."""

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

    def done(self) -> bool:
        return self.finished.is_file()


def gpu_slots(requested: str | None) -> list[str | None]:
    """GPU indices to run on; ``[None]`` (one job at a time, no pinning) when the machine shows no
    NVIDIA GPU. Asked of ``nvidia-smi``, not JAX: this process must not take GPU memory from its
    jobs."""
    if requested is not None:
        gpus = [g.strip() for g in requested.split(",")]
        if not gpus or not all(g.isdigit() for g in gpus):
            raise ConfigError(f"--gpus {requested!r} is not accepted: GPU indices, comma-separated (e.g. 0,2)")
        return gpus
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [g.strip() for g in visible.split(",") if g.strip()] or [None]
    smi = shutil.which("nvidia-smi")
    if smi is None:
        return [None]
    try:
        lines = subprocess.run([smi, "-L"], capture_output=True, text=True, timeout=30).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return [None]
    gpus = [str(i) for i, line in enumerate(lines) if line.startswith("GPU ")]
    return gpus or [None]


def gpu_memory_mib(slots: list[str | None]) -> dict[str, float]:
    """Each GPU slot's total memory [MiB] as ``nvidia-smi`` reports it (by index); a slot it does
    not list, or a machine without it, is left out (its shares are taken as they are)."""
    smi = shutil.which("nvidia-smi")
    if smi is None or slots == [None]:
        return {}
    query = [smi, "--query-gpu=index,memory.total", "--format=csv,noheader,nounits"]
    try:
        lines = subprocess.run(query, capture_output=True, text=True, timeout=30).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return {}
    total = {}
    for line in lines:
        index, _, mib = line.partition(",")
        try:
            total[index.strip()] = float(mib)
        except ValueError:
            continue
    return {s: total[s] for s in slots if s in total and total[s] > 0}


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


@dataclasses.dataclass
class _Running:
    job: Job
    slot: str | None
    proc: subprocess.Popen
    stdout: object
    started: float
    offset: int  # where this start's output begins in the job's log (a resumed job appends)


def run_jobs(
    jobs: list[Job],
    slots: list[str | None],
    log: Callable[[str], None],
    heartbeat_s: float = HEARTBEAT_S,
    on_end: Callable[[dict[str, dict]], None] | None = None,
    memory_mib: dict[str, float] | None = None,
) -> dict[str, dict]:
    """Runs the jobs not finished yet (see the module's docstring); returns, per job this call
    started, ``{"exit": code, "wall_s": seconds, "stage": stage}`` (exit None: not started because
    a job it needs failed; "stopped": running when this call was stopped), and passes the same
    record to ``on_end`` each time a job ends. A SIGTERM or Ctrl-C stops the running jobs; they
    resume when started again. ``memory_mib``: each GPU's memory (None: asked of ``nvidia-smi``,
    :func:`gpu_memory_mib`), which turns shares into fractions of it."""
    by_name = {j.name: j for j in jobs}
    for j in jobs:
        unknown = [n for n in j.needs + j.helps if n not in by_name]
        if unknown:
            raise ValueError(f"job {j.name} needs unknown jobs {unknown}")
    todo = _needed(jobs)
    finished = {j.name for j in jobs if j not in todo}  # done, or no longer needed by anything
    spared = sum(1 for j in jobs if j not in todo and not j.done())
    log(
        f"{len(jobs)} jobs: {len(finished) - spared} finished already, "
        + (f"{spared} no longer needed (what needs them has finished), " if spared else "")
        + f"{len(todo)} to run on {_where(slots)}"
    )
    load = {s: 0.0 for s in slots}
    mib = gpu_memory_mib(slots) if memory_mib is None else memory_mib
    scale = {s: REFERENCE_MIB / mib[s] if s in mib else 1.0 for s in slots}
    running: list[_Running] = []
    failed: set[str] = set()
    out: dict[str, dict] = {}

    def stop(signum, frame):  # the jobs resume from their own checkpoints when started again
        for r in running:
            r.proc.terminate()
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        # a key one of whose jobs finished in an earlier call is in the cache (on the same machine)
        warmed = {j.programs for j in jobs if j.programs and j.done()}
        return _loop(todo, finished, failed, running, out, load, scale, log, heartbeat_s, on_end, warmed)
    finally:
        signal.signal(signal.SIGTERM, previous)
        now = time.perf_counter()
        for r in running:  # stopped (SIGTERM, Ctrl-C): recorded with the time they had
            out[r.job.name] = {"exit": "stopped", "wall_s": now - r.started, "stage": r.job.stage}
            r.proc.terminate()
        if running and on_end is not None:
            on_end(out)


def _loop(todo, finished, failed, running, out, load, scale, log, heartbeat_s, on_end, warmed) -> dict[str, dict]:
    """Starts and reaps jobs until none is left to start or running (``running`` and ``out`` are the
    caller's, so a stopped loop leaves them as they were); ``scale``: each slot's shares to
    fractions of its memory; ``warmed``: the programs keys some job has compiled (see Job.programs)."""
    gpu = list(scale) != [None]
    stage_left = {s: sum(1 for j in todo if j.stage == s) for s in dict.fromkeys(j.stage for j in todo)}
    stage_t0: dict[str, float] = {}
    t0 = last_beat = time.perf_counter()

    def end_of(job: Job, now: float) -> None:
        stage_left[job.stage] -= 1
        if stage_left[job.stage] == 0 and job.stage in stage_t0:
            log(f"stage {job.stage}: {now - stage_t0[job.stage]:.0f} s")

    while todo or running:
        waiting = False  # a job that does the work is ready and waits for GPU memory: helpers hold off
        for job in sorted(todo, key=lambda j: bool(j.helps)):  # the real jobs first, each in its order
            if any(n in failed for n in job.needs):
                todo.remove(job)
                failed.add(job.name)
                out[job.name] = {"exit": None, "wall_s": 0.0, "stage": job.stage}
                log(f"{job.name} not started: a job it needs failed")
                end_of(job, time.perf_counter())
                continue
            if job.helps and not any(t.name in job.helps for t in todo):  # what it helps has started
                todo.remove(job)
                log(f"{job.name} not started: the jobs it helps have started")
                end_of(job, time.perf_counter())
                continue
            if not all(n in finished for n in job.needs):
                continue
            if _waits(job, running, warmed) or (job.helps and waiting):
                continue
            slot = _place(job, load, scale, running)
            if slot is False:
                waiting = waiting or not job.helps
                continue
            todo.remove(job)
            share = _fraction(job.share, scale[slot]) if gpu else 1.0
            running.append(_start(job, slot, share))
            load[slot] += share
            stage_t0.setdefault(job.stage, time.perf_counter())
            where = f"GPU {slot}, {share:.0%} of its memory" if gpu else "this machine"
            log(f"started {job.name} on {where}")
        time.sleep(0.5)
        now = time.perf_counter()
        for r in running:
            if r.job.programs and r.job.programs not in warmed and _printed(r, r.job.compiled):
                warmed.add(r.job.programs)
                log(f"{r.job.name} has compiled its programs: the jobs that share them start")
        if running and now - last_beat >= heartbeat_s:
            last_beat = now
            for r in running:
                log(f"  {r.job.name} ({(now - r.started) / 60:.1f} min): {last_line(r.job.log) or '...'}")
        for r in [r for r in running if r.proc.poll() is not None]:
            running.remove(r)
            r.stdout.close()
            load[r.slot] -= _fraction(r.job.share, scale[r.slot]) if gpu else 1.0
            wall = now - r.started
            code = r.proc.returncode
            if r.job.programs and code == 0:  # what it compiled is in the cache (failed: the next one compiles)
                warmed.add(r.job.programs)
            out[r.job.name] = {"exit": code, "wall_s": wall, "stage": r.job.stage}
            if code == 0 and r.job.done():
                finished.add(r.job.name)
                verdict = "finished"
            else:
                failed.add(r.job.name)
                why = f"exit {code}" if code != 0 else f"exit 0 without {r.job.finished.name}"
                verdict = f"FAILED ({why}; its output: {r.job.log})"
                if r.job.helps:
                    verdict += "; the jobs it helps compile their own programs"
            left = len(todo) + len(running)
            log(
                f"{r.job.name} {verdict} after {wall:.0f} s; {len(out)} done, {left} left, {(now - t0) / 60:.1f} min in"
            )
            end_of(r.job, now)
            if on_end is not None:
                on_end(out)
    return out


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


def _where(slots: list[str | None]) -> str:
    return "this machine (no GPU: one job at a time)" if slots == [None] else f"GPU(s) {', '.join(slots)}"


def _place(job: Job, load: dict, scale: dict, running: list[_Running]):
    """The least-loaded GPU where the job's share fits beside the shares and CUDA contexts
    (:data:`CONTEXT_SHARE`) of the jobs on it, each scaled to the GPU's memory, else False; a job
    larger than a whole GPU runs alone on an idle one."""
    if list(scale) == [None]:
        return None if not running else False
    slot = min(load, key=load.get)
    processes = 1 + sum(r.slot == slot for r in running)
    need = _fraction(job.share, scale[slot]) + CONTEXT_SHARE * processes * scale[slot]
    if load[slot] + need <= 1.0 + 1e-9 or load[slot] == 0.0:
        return slot
    return False


def _fraction(share: float, scale: float) -> float:
    """A share of an 80 GB GPU as a fraction of one whose memory is ``1 / scale`` of that; a share
    of 1 or more is the whole GPU, whatever its size."""
    return share if share >= 1.0 else share * scale


def _waits(job: Job, running: list[_Running], warmed: set[str]) -> bool:
    """Whether ``job`` waits for a running job of its ``programs`` key to compile them."""
    if job.programs is None or job.programs in warmed:
        return False
    return any(r.job.programs == job.programs for r in running)


def _printed(r: _Running, text: str | None) -> bool:
    """Whether the running job's output since its start holds ``text``."""
    if not text:
        return False
    try:
        with open(r.job.log, "rb") as f:
            f.seek(r.offset)
            return text in f.read().decode(errors="replace")
    except OSError:
        return False


def _start(job: Job, slot: str | None, fraction: float) -> _Running:
    """Starts the job's process; on a GPU ``slot`` with ``fraction`` of its memory."""
    env = dict(os.environ)
    if slot is not None:
        env["CUDA_VISIBLE_DEVICES"] = slot
        env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{min(fraction, 0.95):.3f}"
    job.log.parent.mkdir(parents=True, exist_ok=True)
    stdout = open(job.log, "a")  # noqa: SIM115 - closed when the job ends
    stdout.write(f"\n# {time.strftime('%Y-%m-%d %H:%M:%S')} started\n")
    stdout.flush()
    argv = [sys.executable, *job.argv()]
    proc = subprocess.Popen(argv, stdout=stdout, stderr=subprocess.STDOUT, env=env)
    return _Running(job, slot, proc, stdout, time.perf_counter(), stdout.tell())
