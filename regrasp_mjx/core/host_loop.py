"""What the host loops of training (:mod:`regrasp_mjx.workflows.trainer`) and distillation
(:mod:`regrasp_mjx.workflows.distillation`) share: where the wall-clock time goes (:class:`Phases`), the choice of the
exported network by validation (:class:`BestOf`), the JSONL run log with its TensorBoard mirror
(:class:`RunLog`) and the progress line's ETA (:func:`eta`); and what every long command line shares:
one run per output folder (:func:`folder_lock`), Ctrl-C as one line (:func:`run_command`) and a
bound on the compiled programs one long process keeps (:func:`release_programs`).

One format for both: a log row per member and epoch (iteration, for distillation) holding
``validation`` and ``test`` summaries of :func:`regrasp_mjx.envs.rollout.summarize`, the losses, and
``timing``: seconds per phase since the row before (the profile of a run: where the host waits on
the device, plans, evaluates and writes).
"""

from __future__ import annotations

import _thread
import contextlib
import fcntl
import gc
import json
import math
import os
import signal
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import jax

from regrasp_mjx.core import xla_flags
from regrasp_mjx.core.atomic import dumps, write_text


class Phases:
    """Wall-clock seconds per named phase (phases may repeat): :meth:`take` gives those since the last
    take, :meth:`totals` those of the whole run."""

    def __init__(self) -> None:
        self._seconds: dict[str, float] = defaultdict(float)
        self._totals: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._seconds[name] += time.perf_counter() - t0

    def add(self, name: str, seconds: float) -> None:
        self._seconds[name] += seconds

    def take(self) -> dict[str, float]:
        """The sums since the last take (rounded to 0.1 ms), and a fresh start."""
        out = {k: round(v, 4) for k, v in self._seconds.items()}
        for k, v in self._seconds.items():
            self._totals[k] += v
        self._seconds.clear()
        return out

    def totals(self) -> dict[str, float]:
        """Every phase's seconds since the start (what is not taken yet included)."""
        self.take()
        return {k: round(v, 4) for k, v in self._totals.items()}


class BestOf:
    """Per member, the best validation score so far and the step (epoch or iteration) it came at.

    The lists are held, not copied, so a checkpoint's ``meta`` can own them. A score equal to the
    best counts as better: of equal networks the later one, trained longer, is exported.
    """

    def __init__(self, score: list[float], step: list[int | None]):
        if len(score) != len(step):
            raise ValueError(f"BestOf: {len(score)} scores against {len(step)} steps; one of each per member")
        self.score, self.step = score, step

    @classmethod
    def fresh(cls, members: int) -> BestOf:
        return cls([-1.0] * members, [None] * members)

    def update(self, scores: Sequence[float], step: int) -> list[int]:
        """The members whose ``scores`` match or beat their best (recorded at ``step``)."""
        better = [m for m, s in enumerate(scores) if s >= self.score[m]]
        for m in better:
            self.score[m], self.step[m] = float(scores[m]), step
        return better


class RunLog:
    """A JSONL log, one object per line, appended row by row; each row's finite numbers also go to
    its member's TensorBoard writer when one is given (``writers[i]`` for ``rows[i]``)."""

    def __init__(self, path: Path, writers: Sequence[Any] = ()):
        self.path, self.writers = path, list(writers)

    def drop_after(self, key: str, last: int) -> None:
        """Keeps the rows whose ``key`` is at most ``last`` (a resumed run writes the rest again)."""
        if self.path.exists():
            keep = [x for x in self.path.read_text().splitlines() if x.strip() and json.loads(x)[key] <= last]
            write_text(self.path, "".join(x + "\n" for x in keep))

    def write(self, rows: Sequence[dict[str, Any]], step_key: str = "epoch") -> None:
        with open(self.path, "a") as f:
            f.write("".join(dumps(r) + "\n" for r in rows))
        for writer, row in zip(self.writers, rows):
            if writer is None:
                continue
            for k, v in _scalars(row).items():
                writer.add_scalar(k, v, row[step_key])
            writer.flush()

    def close(self) -> None:
        for writer in self.writers:
            if writer is not None:
                writer.close()


def _scalars(row: dict[str, Any], prefix: str = "") -> dict[str, float]:
    """The row's finite numbers, nested dicts flattened as ``outer/inner``."""
    out = {}
    for k, v in row.items():
        if isinstance(v, dict):
            out.update(_scalars(v, f"{prefix}{k}/"))
        elif isinstance(v, float) and math.isfinite(v):
            out[prefix + k] = v
    return out


def tensorboard_writer(folder: Path):
    """A TensorBoard writer in ``folder``, or None when tensorboardX is not installed (the JSONL log
    has everything)."""
    try:
        from tensorboardX import SummaryWriter  # here: its import (protobuf) only for runs that log to TensorBoard
    except ImportError:
        return None
    return SummaryWriter(str(folder))


def eta(done: int, total: int, seconds: float) -> str:
    """``ETA x.x min`` from ``done`` of ``total`` steps in ``seconds``."""
    left = (seconds / done) * (total - done) if done else float("nan")
    return f"ETA {left / 60:.1f} min"


def mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} mm"


def epoch_line(epochs: int, rows: list[dict[str, Any]], demos_received: list[int], eta_text: str) -> str:
    """A training epoch's progress line: every member's numbers (its log rows), separated by slashes."""
    each = lambda xs, f="{:.3f}": "/".join(f.format(x) for x in xs)  # noqa: E731
    col = lambda k, sub=None: [r[k] if sub is None else r[k][sub] for r in rows]  # noqa: E731
    r0 = rows[0]
    return (
        f"epoch {r0['epoch']}/{epochs}  val success {each(col('validation', 'success_rate'))}  "
        f"test success {each(col('test', 'success_rate'))} "
        f"(collision {each(col('test', 'collision_rate'))}, "
        f"path {'/'.join(mm(x) for x in col('test', 'path_length_mm'))})  "
        f"return {each(col('return'), '{:+.3f}')}  critic {each(col('critic_loss'), '{:.4f}')}  "
        f"actor {each(col('actor_loss'), '{:+.5f}')}  Q {each(col('q'), '{:+.3f}')}  "
        f"E_R {each(col('E_R'))}  E_T {each(col('E_T'))}  demos+ {each(demos_received, '{}')}  "
        f"{r0['env_steps_per_s']:,.0f} env-steps/s  {r0['updates_per_s']:,.0f} updates/s  {eta_text}"
    )


# ---- what every long command line shares: one run per folder, and Ctrl-C without a traceback -----


class FolderInUse(RuntimeError):
    """Another process holds the output folder's lock."""


def _in_use(out: Path, holder: str) -> str:
    return f"--out {out} is in use by another run ({holder}); accepted: another --out, or wait for that run to end"


def folder_in_use(out: Path) -> str | None:
    """Why ``out`` cannot be written now: another live process holds its lock (:func:`folder_lock`);
    None when none does. Creates nothing: commands ask it first, so a live run's folder is named as
    in use rather than as an earlier run."""
    try:
        f = open(out / ".lock")
    except OSError:  # no folder, or no lock file: no run has held it
        return None
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _in_use(out, f.read().strip() or "another process")
    return None


@contextlib.contextmanager
def folder_lock(out: Path, shared: bool = False):
    """Holds ``out/.lock`` (an advisory ``flock``) while a run writes into ``out``: a second run
    into the same folder is refused while the first lives; the kernel drops the lock when its
    process ends, however it ends, so a killed run leaves no stale lock. ``shared``: runs that each
    write parts of their own (shards) hold it together, and a run that needs the folder alone is
    refused while any of them lives (and they while it does)."""
    out.mkdir(parents=True, exist_ok=True)
    f = open(out / ".lock", "a+")
    try:
        try:
            fcntl.flock(f, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            raise FolderInUse(_in_use(out, f.read().strip() or "another process")) from None
        if not shared:  # shared holders leave the file as it is: they would write over each other
            f.seek(0)
            f.truncate()
            f.write(f"pid {os.getpid()}")
            f.flush()
        yield
    finally:
        f.close()


def run_command(main: Callable[[], int], again: str) -> int:
    """Runs a command line's ``main`` with the compilation cache every command shares
    (:func:`regrasp_mjx.core.xla_flags.cache_folder`: a program another command compiled loads
    instead); Ctrl-C prints one line saying how to go on (``again``) and exits 130, never a traceback.

    Python drops (prints as "Exception ignored") a KeyboardInterrupt raised inside a garbage-collector
    callback (XLA's ``_xla_gc_callback``) or a ``__del__``, and the command would go on: a Ctrl-C that
    lands there is raised again a moment later, where it ends the command (:func:`_interrupt_later`)."""
    jax.config.update("jax_compilation_cache_dir", xla_flags.cache_folder())
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, _on_sigint) if main_thread else None
    previous_hook, sys.unraisablehook = sys.unraisablehook, _unraisable(sys.unraisablehook)
    try:
        return main()
    except KeyboardInterrupt as err:
        if main_thread:
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # an interrupt raised again late is dropped
        done = f"{err}; " if str(err) else ""  # what the command stopped (e.g. the jobs it started)
        print(f"interrupted; {done}{again}", file=sys.stderr)
        return 130
    finally:
        sys.unraisablehook = previous_hook
        if main_thread:
            signal.signal(signal.SIGINT, previous)


def _interrupt_later() -> None:
    threading.Timer(0.05, _thread.interrupt_main).start()


def _on_sigint(signum, frame) -> None:
    """KeyboardInterrupt, unless Python would drop it here (a gc callback or ``__del__`` runs)."""
    callbacks = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    while frame is not None:
        if frame.f_code in callbacks or frame.f_code.co_name == "__del__":
            _interrupt_later()
            return
        frame = frame.f_back
    raise KeyboardInterrupt


def _unraisable(hook):
    """``sys.unraisablehook`` that raises a dropped KeyboardInterrupt again, silently, and passes
    everything else on to ``hook``."""

    def unraisable(info) -> None:
        if info.exc_type is not None and issubclass(info.exc_type, KeyboardInterrupt):
            _interrupt_later()
        else:
            hook(info)

    return unraisable


# Every program XLA:CPU compiles keeps its code in memory maps of its own (about 900 for the shielded
# environment step, thousands for a closed loop), and Linux refuses a process more than
# vm.max_map_count (65,530 by default): the next mmap fails and XLA crashes where it maps, a
# segfault while compiling or an abort while loading a cached program. One process that compiles
# many policies' programs (``compare`` over every shipped policy, a test worker) crosses it.
MAPS_HIGH = 30_000


def release_programs(high: int = MAPS_HIGH) -> bool:
    """Drops every compiled program (``jax.clear_caches()``; what is used again compiles again)
    when this process holds more than ``high`` memory maps; whether it did. Not on Linux: never."""
    try:
        with open("/proc/self/maps") as f:
            count = sum(1 for _ in f)
    except OSError:
        return False
    if count <= high:
        return False
    jax.clear_caches()
    gc.collect()
    return True
