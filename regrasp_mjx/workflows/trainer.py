"""The host loop of one training run: :class:`Run` drives the jitted :class:`Learner` epoch by epoch.

Python runs only between iterations: the planner exchange (:mod:`regrasp_mjx.agents.ddpg_bc.exchange`),
and per epoch the evaluation on the test set and on validation problems of the run's own seed (which
choose the exported policy), the log line, TensorBoard and JSONL logs, and an atomic checkpoint
(:mod:`regrasp_mjx.agents.ddpg_bc.checkpoint`). It sits above the inference layer (it exports,
tests and distils policies), below the CLIs; ``python -m regrasp_mjx.train`` is its command line.
At the end each member's policy is exported and tested, distilled when asked,
and the best seed of each setting copied to ``OUT/policy``. In a distributed run every process runs
this loop; process 0 writes (:mod:`regrasp_mjx.core.distributed`).
"""

from __future__ import annotations

import dataclasses
import os
import time
import uuid
from pathlib import Path
from typing import Any

import jax
import numpy as np

from regrasp_mjx.agents.ddpg_bc import checkpoint
from regrasp_mjx.agents.ddpg_bc.config import (
    TrainConfig,
)
from regrasp_mjx.agents.ddpg_bc.exchange import PlannerExchange
from regrasp_mjx.agents.ddpg_bc.learner import Learner, TrainingState
from regrasp_mjx.core import distributed, geometry
from regrasp_mjx.core.atomic import atomic_write, write_json
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.core.host_loop import BestOf, Phases, RunLog, epoch_line, eta, folder_lock, mm, tensorboard_writer
from regrasp_mjx.envs.rollout import summarize
from regrasp_mjx.inference.policy import load_policy, save_policy
from regrasp_mjx.inference.testset_plans import outcomes
from regrasp_mjx.planning import demonstrations
from regrasp_mjx.planning.episodes import Demos, DemosError, check_made_for, load_demos
from regrasp_mjx.workflows.distillation import distill
from regrasp_mjx.workflows.epochs import EpochAcc, Loop, epoch_rows
from regrasp_mjx.world.sampling import load_testset
from regrasp_mjx.world.testsets import make_testset

VALIDATION_SEED = 1_000_003


def _copy_policy(src: Path, dst: Path) -> None:
    for name in ("policy.npz", "policy.json"):
        atomic_write(dst / name, lambda f, src=src / name: f.write(src.read_bytes()))


def check_demos(demos: Demos, env: EnvConfig, path: Path) -> Demos:
    """``demos`` (from ``path``), refused (:class:`DemosError`) where made for another scene or task
    than ``env``'s or with observations of another width than its task's."""
    check_made_for(demos, env, path)
    width = geometry.OBS_SIZE_GENERAL if env.task.general else geometry.OBS_SIZE
    if demos.obs.shape[1] != width:
        raise DemosError(
            f"{path} holds observations of {demos.obs.shape[1]} numbers, this run's "
            f"task observes {width}: demonstrations of the paper's task (21) train a paper-task run, those of "
            "a general task (37; python -m regrasp_mjx.demos --task general) a general one"
        )
    return demos


class Run:
    """One training run in ``out``; :meth:`train` is resumable."""

    def __init__(self, cfg: TrainConfig, out: Path, demos_dir: Path | None, testset: Path, quiet: bool = False):
        self.cfg, self.out, self.quiet = cfg, out, quiet
        self.ckpt = out / "checkpoint"
        self.phases = Phases()  # where the run's time goes; every log row and final_eval.json say
        with self.phases("setup"):
            self.testset, _ = load_testset(testset)
            # Model selection uses problems of their own (never the test set): validation_size from another seed.
            self.valset = make_testset(cfg.validation_size, VALIDATION_SEED + cfg.seed, cfg.env)
        with self.phases("demos"):
            self.demos = self._demos(demos_dir)
        with self.phases("setup"):
            self.learner = Learner(cfg)

    def log(self, msg: str) -> None:
        if not self.quiet and distributed.is_main():
            print(msg, flush=True)

    def _demos(self, demos_dir: Path | None):
        return check_demos(self._load_or_build_demos(demos_dir), self.cfg.env, demos_dir or self.out / "demos")

    def _load_or_build_demos(self, demos_dir: Path | None):
        if demos_dir is not None:
            return load_demos(demos_dir)
        path = self.out / "demos"
        if not (path / "demos.npz").exists() and distributed.is_main():
            self.log(f"building {self.cfg.num_demos} demonstrations in {path} (BIT* reverse) ...")
            demonstrations.build(
                self.cfg.num_demos,
                path,
                seed=self.cfg.seed,
                workers=self.cfg.planner_workers or max(1, (os.cpu_count() or 2) - 1),
                budget_s=self.cfg.planner_budget_s,
                scene=self.cfg.env.scene,
                task=self.cfg.env.task,
                replay_batch=64,
                quiet=self.quiet,
            )
        distributed.sync("demos")  # the others wait for process 0's set
        return load_demos(path)

    # ---- the loop ----------------------------------------------------------------------------
    def member_dir(self, m: int) -> Path:
        """Where member ``m`` writes its policies: OUT itself for a single learner, ``OUT/seedS`` for
        several seeds, ``OUT/SETTING/seedS`` for several settings."""
        cfg = self.cfg
        setting = cfg.member_setting(m)[0]
        if cfg.num_members == 1:
            return self.out
        return (self.out / setting if setting else self.out) / f"seed{cfg.member_seed(m)}"

    def setting_dir(self, m: int) -> Path:
        """Where the best seed of member ``m``'s setting is copied: OUT, or ``OUT/SETTING``."""
        setting = self.cfg.member_setting(m)[0]
        return self.out / setting if setting else self.out

    def _export(self, folder: Path, host: tuple[Any, Any], m: int, training: dict[str, Any]) -> None:
        """Writes member ``m`` of ``host`` (``(actor, normaliser)`` from :meth:`_host_policy`)."""
        if not distributed.is_main():
            return
        pick = lambda tree: jax.tree.map(lambda x: x[m], tree)  # noqa: E731
        cfg = self.cfg
        training = {
            "config": checkpoint.config_json(cfg),
            "setting": cfg.member_setting(m)[0] or None,
            "seed": cfg.member_seed(m),
            "actor_ema": cfg.actor_ema,
            **training,
        }
        params, normalizer = host
        save_policy(folder, pick(params), pick(normalizer), cfg.hidden, cfg.env, extra={"training": training})

    def _host_policy(self, ts: TrainingState) -> tuple[Any, Any]:
        """Every member's exported actor and normaliser as numpy (a collective across processes)."""
        return distributed.to_host((self.learner.policy_params(ts), ts.normalizer))

    def train(self, resume: bool = False) -> dict[str, Any]:
        cfg, learner, seeds, phases = self.cfg, self.learner, self.cfg.num_members, self.phases
        main = distributed.is_main()
        demos = {k: np.asarray(getattr(self.demos, k), np.float32) for k in ("obs", "action", "reward", "next_obs")}
        demos["terminal"] = np.asarray(self.demos.done, np.float32)
        with phases("setup"):
            ts = learner.init(demos)
        best = BestOf.fresh(seeds)
        meta: dict[str, Any] = {
            "epoch": 0,
            "iteration": 0,
            "demos_received": [0] * seeds,
            "planned": [0] * seeds,
            "best_val": best.score,
            "best_epoch": best.step,
            "rng": np.random.default_rng(cfg.seed).bit_generator.state,
        }
        restart = resume and not (self.ckpt / "meta.json").is_file()  # stopped before its first checkpoint
        if restart:
            self.log("no checkpoint yet: starting at epoch 0 (the demonstrations built so far are kept)")
            resume = False
        if resume:  # a checkpoint of other settings is refused here, before the run writes anything
            ts, meta = checkpoint.load(self.ckpt, ts, cfg)
            ts = learner.place(ts)
            best = BestOf(meta["best_val"], meta["best_epoch"])
            self.log(f"resumed from {self.ckpt} at epoch {meta['epoch']}")
        log = RunLog(
            self.out / "log.jsonl",
            [tensorboard_writer(self.member_dir(m) / "tb") if main else None for m in range(seeds)],
        )
        if main and (restart or resume):  # epochs after the checkpoint (all, without one) run again
            log.drop_after("epoch", meta["epoch"] if resume else -1)
        # one id per run, kept across resumes (a checkpoint from before run ids gets one now)
        meta.setdefault("run_id", uuid.uuid4().hex[:12])
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        explos = [cfg.member_setting(m)[1] for m in range(seeds)]
        targeted = any(x.targeted_eps > 0 for x in explos)
        loop = Loop(
            ts=ts,
            meta=meta,
            best=best,
            rng=rng,
            explos=explos,
            exchange=PlannerExchange(cfg, learner) if targeted else None,
            log=log,
            # numpy, not device arrays: in a distributed run a host value given to a jitted program is
            # the same on every process and is placed on the global mesh as such
            test=jax.tree.map(lambda x: np.asarray(x, np.float32), self.testset),
            val=jax.tree.map(lambda x: np.asarray(x, np.float32), self.valset),
            t_start=time.perf_counter(),
        )
        try:
            for epoch in range(meta["epoch"], cfg.epochs):
                self._epoch(loop, epoch)
            with phases("checkpoint"):
                loop.writer.wait()  # the last checkpoint is on disk before the run reports
        finally:
            if loop.exchange is not None:
                loop.exchange.close()
            log.close()
        return self.finish(loop.ts, loop.last, loop.compile_s, meta, time.perf_counter() - loop.t_start)

    def _epoch(self, loop: Loop, epoch: int) -> None:
        """Epoch ``epoch`` (0-based): its iterations, the evaluation and selection, the checkpoint when
        due, the log rows and the progress line."""
        cfg, learner, meta, phases = self.cfg, self.learner, loop.meta, self.phases
        t_epoch = time.perf_counter()
        acc = EpochAcc()
        for _ in range(cfg.iterations_per_epoch):
            e_r, e_t = np.array([x.at(meta["iteration"]) for x in loop.explos], np.float32).T
            if loop.compile_s is None:  # the first call traces and compiles: the longest wait of a short run
                self.log(
                    "compiling the iteration program (once per process; tens of seconds on a CPU, "
                    "less with a warm compilation cache) ..."
                )
            t_it = time.perf_counter()
            loop.ts, metrics, outcome, problems = learner.iteration(loop.ts, e_r)  # queued behind `pending`
            if loop.compile_s is None:
                loop.compile_s = time.perf_counter() - t_it  # tracing and compiling block the call
                phases.add("compile", loop.compile_s)
                self.log(f"compiled the iteration program in {loop.compile_s:.1f} s (backend {jax.default_backend()})")
                self.log(
                    f"epoch {epoch + 1}/{cfg.epochs}: {cfg.iterations_per_epoch} iterations, then the evaluation "
                    "(its programs compile on the first epoch) ..."
                )
            meta["iteration"] += 1
            if acc.pending is not None:
                self._after_iteration(loop, acc)
            acc.pending = (outcome, metrics, problems, e_t)
        self._after_iteration(loop, acc)
        # the iterations' rate, host work overlapped; the process's first epoch less the compile
        iter_s = time.perf_counter() - t_epoch - ((loop.compile_s or 0.0) if loop.epochs_run == 0 else 0.0)
        eval_s = time.perf_counter()
        evs, vas = self._evaluate_and_select(loop.ts, loop.test, loop.val, loop.best, epoch + 1)
        eval_s = time.perf_counter() - eval_s
        epoch_s = time.perf_counter() - t_epoch
        meta["epoch"] = epoch + 1
        meta["rng"] = loop.rng.bit_generator.state
        meta["config"] = checkpoint.config_json(cfg)
        if (epoch + 1) % cfg.checkpoint_every == 0 or epoch + 1 == cfg.epochs:
            with phases("checkpoint"):  # the copy to the host; the file is written beside the training
                loop.writer.save(self.ckpt, loop.ts, meta)
        timing = phases.take()  # this epoch's seconds per phase (the first epoch's hold the set-up)
        per_s = cfg.iterations_per_epoch / max(iter_s, 1e-9)  # iterations per second
        seconds = {"epoch_s": epoch_s, "eval_s": eval_s, "wall_s": time.perf_counter() - loop.t_start}
        rows = epoch_rows(cfg, meta, acc, evs, vas, loop.explos, per_s, seconds, timing)
        if distributed.is_main():
            with phases("log"):
                loop.log.write(rows)
        loop.epochs_run += 1
        trained_s = time.perf_counter() - loop.t_start - (loop.compile_s or 0.0)
        # the ETA is measured on the epochs alone: the final tests (and distillation) come after it
        after = "the final tests" + (" and distillation" if cfg.distill.iterations > 0 else "")
        left = eta(loop.epochs_run, loop.epochs_run + cfg.epochs - epoch - 1, trained_s)
        self.log(epoch_line(cfg.epochs, rows, meta["demos_received"], f"{left} for the epochs, then {after}"))
        loop.last = rows

    def _after_iteration(self, loop: Loop, acc: EpochAcc) -> None:
        """The host's part of the finished iteration ``acc.pending``, run while the next one is on the
        device: its outcome and metrics fetched (waiting for it), its chosen failed episodes sent to
        the planners and the demonstrations that came back inserted (behind the queued iteration)."""
        outcome, metrics, problems, e_t = acc.pending
        with self.phases("iterations"):  # waiting for the device
            outcome = distributed.to_host(outcome)  # Rollout of [seed, env]
        with self.phases("exchange"):
            acc.metrics.append(distributed.to_host(dict(metrics)))
            acc.outcomes.append(outcome)
            if loop.exchange is not None:
                loop.ts = loop.exchange.after_iteration(loop.ts, outcome.success, problems, e_t, loop.rng, loop.meta)

    def _evaluate_and_select(self, ts: TrainingState, test: Any, val: Any, best: BestOf, epoch: int):
        """Each member's bare success on the test set and the validation problems; the members whose
        validation success is at least their best so far export this epoch's policy (``best``
        records it). Returns the two lists of summaries."""
        learner, members, phases = self.learner, self.cfg.num_members, self.phases
        with phases("evaluate"):
            actor = learner.policy_params(ts)
            ev_all = distributed.to_host(learner.evaluate(actor, ts.normalizer, test))
            va_all = distributed.to_host(learner.evaluate_q(actor, ts.normalizer, val, ts.critic))
            member = lambda tree, m: jax.tree.map(lambda x: x[m], tree)  # noqa: E731
            evs = [summarize(member(ev_all[0], m), "bare") for m in range(members)]
            vas = [summarize(member(va_all[0], m), "bare", q_start=va_all[1][m]) for m in range(members)]
        with phases("export"):
            better = best.update([va["success_rate"] for va in vas], epoch)
            host = self._host_policy(ts) if better else None
            for m in better:  # export the best by validation
                training = {"epoch": epoch, "validation_success": vas[m]["success_rate"]}
                self._export(self.member_dir(m) / "policy", host, m, training)
        return evs, vas

    def finish(
        self,
        ts: TrainingState,
        last: list[dict[str, Any]],
        compile_s: float | None,
        meta: dict[str, Any],
        train_s: float,
    ) -> dict[str, Any]:
        """Exports each member's last policy beside its best (by validation), tests the best ones
        bare and shielded, distils them when ``distill.iterations`` > 0, and copies each setting's
        best seed (by validation) to ``OUT/policy`` (``OUT/SETTING/policy`` for several settings),
        its student to ``.../student/policy``."""
        cfg, t_finish = self.cfg, time.perf_counter()
        # the bare and shielded tests compile their programs first: a silent wait without this line
        self.log("final tests on the test set (bare and shielded; their programs compile first) and export ...")
        host = self._host_policy(ts)  # a collective: every process
        if not distributed.is_main():
            return {}  # the tests, distillation and the summary are process 0's
        members = []
        for m in range(cfg.num_members):
            self._export(self.member_dir(m) / "policy_last", host, m, {"epoch": meta["epoch"]})
            policy_dir = self.member_dir(m) / "policy"
            members.append(
                {
                    "setting": cfg.member_setting(m)[0] or None,
                    "seed": cfg.member_seed(m),
                    "policy": str(policy_dir),
                    "best_epoch": meta["best_epoch"][m],
                    "best_validation_success": meta["best_val"][m],
                    "test": self._final_test(policy_dir),
                    "last_epoch": last[m] if last else None,
                }
            )
            ev = members[-1]["test"]
            self.log(
                f"{members[-1]['setting'] or 'seed'} {members[-1]['seed']}: exported {policy_dir} (epoch "
                f"{meta['best_epoch'][m]}, best on validation); on the test set: "
                f"success {ev['bare']['success_rate']:.3f} bare, {ev['shielded']['success_rate']:.3f} shielded; "
                f"collision {ev['bare']['collision_rate']:.3f} bare; path {mm(ev['bare']['path_length_mm'])}"
            )
        with self.phases("distill"):
            students = self.distill(members) if cfg.distill.iterations > 0 else None
        groups: dict[str, dict[str, Any]] = {}
        for m0 in range(0, cfg.num_members, cfg.num_seeds):  # one group of seeds per setting
            group = range(m0, m0 + cfg.num_seeds)
            best = max(group, key=lambda m: meta["best_val"][m])
            home = self.setting_dir(m0)
            if cfg.num_members > 1:
                _copy_policy(Path(members[best]["policy"]), home / "policy")
            entry = {**members[best], "policy": str(home / "policy")}
            if students is not None:
                top = max(group, key=lambda m: students[m]["best_validation_success"])
                if cfg.num_members > 1:
                    _copy_policy(Path(students[top]["student"]), home / "student" / "policy")
                entry["student"] = {**students[top], "student": str(home / "student" / "policy")}
            groups[cfg.member_setting(m0)[0]] = entry
        # every phase summed over this process's run (a resumed run counts from its resume)
        timing = {**self.phases.totals(), "train": train_s, "finish": time.perf_counter() - t_finish}
        final: dict[str, Any] = {"compile_s": compile_s, "timing": timing, "seeds": members}
        if students is not None:
            final["students"] = students
        if cfg.settings:
            final["settings"] = groups
        else:
            final = {**groups[""], **final}
        write_json(self.out / "final_eval.json", final)
        return final

    def _final_test(self, policy_dir: Path) -> dict[str, Any]:
        with self.phases("final_test"):
            return outcomes(load_policy(policy_dir), self.testset)  # the exported file, as deployed

    def distill(self, members: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """Each member's exported policy teaches a student (``MEMBER_DIR/student``), one after another."""

        students = []
        for m, mem in enumerate(members):
            cfg = dataclasses.replace(self.cfg.distill, seed=mem["seed"])
            folder = self.member_dir(m) / "student"
            self.log(  # the student's programs compile before its first line: tens of seconds on a CPU
                f"{mem['setting'] or 'seed'} {mem['seed']}: distilling {mem['policy']} into {folder} "
                "(compiling the distillation programs first) ..."
            )
            with folder_lock(folder):  # as the distill command takes it: no second distillation into it meanwhile
                result = distill(load_policy(mem["policy"]), folder, cfg, self.testset, mem["policy"], self.quiet)
            students.append({"setting": mem["setting"], "seed": mem["seed"], **result})
        return students
