"""The host loop of one training run: :class:`Run` drives the jitted :class:`Learner` epoch by epoch.

Python runs only between iterations: the planner exchange (:mod:`regrasp_mjx.agents.ddpg_bc.exchange`),
and per epoch the evaluation on the test set and on validation problems of the run's own seed (which
choose the exported policy), the log line, TensorBoard and JSONL logs, and an atomic checkpoint
(:mod:`regrasp_mjx.agents.ddpg_bc.checkpoint`). It sits above the inference layer (it exports,
tests and distils policies), beside the CLIs; ``python -m regrasp_mjx.train`` is its command line. At the end each member's policy is exported and tested, distilled when asked,
and the best seed of each setting copied to ``OUT/policy``. In a distributed run every process runs
this loop; process 0 writes (:mod:`regrasp_mjx.distributed`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import uuid
from pathlib import Path
from typing import Any

import jax
import numpy as np

from regrasp_mjx import demos as demos_cli
from regrasp_mjx import distributed, geometry
from regrasp_mjx.agents.ddpg_bc import checkpoint
from regrasp_mjx.agents.ddpg_bc.config import (
    TrainConfig,
)
from regrasp_mjx.agents.ddpg_bc.exchange import PlannerExchange
from regrasp_mjx.agents.ddpg_bc.learner import Learner, TrainingState
from regrasp_mjx.atomic import atomic_write, write_json, write_text
from regrasp_mjx.distill import distill
from regrasp_mjx.evaluate import outcomes
from regrasp_mjx.planning.episodes import DemosError, load_demos
from regrasp_mjx.policy import load_policy, save_policy
from regrasp_mjx.rollout import summarize
from regrasp_mjx.sampling import PAPER300, load_testset
from regrasp_mjx.testset import make_testset

VALIDATION_SEED = 1_000_003
DEFAULT_TESTSET = PAPER300


def _copy_policy(src: Path, dst: Path) -> None:
    for name in ("policy.npz", "policy.json"):
        atomic_write(dst / name, lambda f, src=src / name: f.write(src.read_bytes()))


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} mm"


def _progress_line(cfg: TrainConfig, rows: list[dict[str, Any]], meta: dict[str, Any], eta_s: float) -> str:
    """The epoch's log line: every member's numbers, separated by slashes."""
    each = lambda xs, f="{:.3f}": "/".join(f.format(x) for x in xs)  # noqa: E731
    col = lambda k, sub=None: [r[k] if sub is None else r[k][sub] for r in rows]  # noqa: E731
    r0 = rows[0]
    return (
        f"epoch {r0['epoch']}/{cfg.epochs}  val success {each(col('validation', 'success_rate'))}  "
        f"test success {each(col('test', 'success_rate'))} "
        f"(collision {each(col('test', 'collision_rate'))}, path {'/'.join(_mm(x) for x in col('test', 'path_length_mm'))})  "
        f"return {each(col('return'), '{:+.3f}')}  critic {each(col('critic_loss'), '{:.4f}')}  "
        f"actor {each(col('actor_loss'), '{:+.5f}')}  Q {each(col('q'), '{:+.3f}')}  "
        f"E_R {each(col('E_R'))}  E_T {each(col('E_T'))}  demos+ {each(meta['demos_received'], '{}')}  "
        f"{r0['env_steps_per_s']:,.0f} env-steps/s  {r0['updates_per_s']:,.0f} updates/s  "
        f"ETA {eta_s / 60:.1f} min"
    )


class Run:
    """One training run in ``out``; :meth:`train` is resumable."""

    def __init__(self, cfg: TrainConfig, out: Path, demos_dir: Path | None, testset: Path, quiet: bool = False):
        self.cfg, self.out, self.quiet = cfg, out, quiet
        self.ckpt = out / "checkpoint"
        self.testset, _ = load_testset(testset)
        # Model selection uses problems of their own (never the test set): validation_size from another seed.

        self.valset = make_testset(cfg.validation_size, VALIDATION_SEED + cfg.seed, cfg.env)
        self.demos = self._demos(demos_dir)
        self.learner = Learner(cfg)

    def log(self, msg: str) -> None:
        if not self.quiet and distributed.is_main():
            print(msg, flush=True)

    def _demos(self, demos_dir: Path | None):
        demos = self._load_or_build_demos(demos_dir)
        width = geometry.OBS_SIZE_GENERAL if self.cfg.env.task.general else geometry.OBS_SIZE
        if demos.obs.shape[1] != width:
            raise DemosError(
                f"{demos_dir or self.out / 'demos'} holds observations of {demos.obs.shape[1]} numbers, this run's "
                f"task observes {width}: demonstrations of the paper's task (21) train a paper-task run, those of "
                "a general task (37; python -m regrasp_mjx.demos --task general) a general one"
            )
        return demos

    def _load_or_build_demos(self, demos_dir: Path | None):
        if demos_dir is not None:
            return load_demos(demos_dir)
        path = self.out / "demos"
        if not (path / "demos.npz").exists() and distributed.is_main():
            self.log(f"building {self.cfg.num_demos} demonstrations in {path} (BIT* reverse) ...")
            demos_cli.build(
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
        demos = load_demos(path)
        env_meta = demos.meta.get("settings", {}).get("env", {})
        if env_meta and env_meta.get("scene") != dataclasses.asdict(self.cfg.env.scene):
            raise DemosError(f"{path} was made for scene {env_meta.get('scene')}, this run uses {self.cfg.env.scene}")
        return demos

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

    def _truncate_log(self, epoch: int) -> None:
        """Drops log rows of epochs after the checkpoint (they will be run again)."""
        path = self.out / "log.jsonl"
        if path.exists() and distributed.is_main():
            keep = [x for x in path.read_text().splitlines() if x.strip() and json.loads(x)["epoch"] <= epoch]
            write_text(path, "".join(x + "\n" for x in keep))

    def train(self, resume: bool = False) -> dict[str, Any]:
        cfg, learner, seeds = self.cfg, self.learner, self.cfg.num_members
        demos = {k: np.asarray(getattr(self.demos, k), np.float32) for k in ("obs", "action", "reward", "next_obs")}
        demos["terminal"] = np.asarray(self.demos.done, np.float32)
        ts = learner.init(demos)
        meta: dict[str, Any] = {
            "epoch": 0,
            "iteration": 0,
            "demos_received": [0] * seeds,
            "planned": [0] * seeds,
            "best_val": [-1.0] * seeds,
            "best_epoch": [None] * seeds,
            "rng": np.random.default_rng(cfg.seed).bit_generator.state,
        }
        if resume:
            ts, meta = checkpoint.load(self.ckpt, ts, cfg)
            ts = learner.place(ts)
            self.log(f"resumed from {self.ckpt} at epoch {meta['epoch']}")
            self._truncate_log(meta["epoch"])
        # one id per run, kept across resumes (a checkpoint from before run ids gets one now)
        meta.setdefault("run_id", uuid.uuid4().hex[:12])
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        # numpy, not device arrays: in a distributed run a host value given to a jitted program is
        # the same on every process and is placed on the global mesh as such
        test = jax.tree.map(lambda x: np.asarray(x, np.float32), self.testset)
        val = jax.tree.map(lambda x: np.asarray(x, np.float32), self.valset)
        explos = [cfg.member_setting(m)[1] for m in range(seeds)]
        targeted = any(x.targeted_eps > 0 for x in explos)
        exchange = PlannerExchange(cfg, learner) if targeted else None
        log_path = self.out / "log.jsonl"
        main = distributed.is_main()
        writers = [self._tensorboard(self.member_dir(m)) if main else None for m in range(seeds)]
        steps_per_iter = seeds * cfg.num_envs * cfg.env.horizon
        t_start, compile_s, last, epochs_run = time.perf_counter(), None, [], 0
        try:
            for epoch in range(meta["epoch"], cfg.epochs):
                t_epoch = time.perf_counter()
                metrics_acc: list[dict[str, np.ndarray]] = []
                outcomes = []
                iter_s, timed = 0.0, 0
                for _ in range(cfg.iterations_per_epoch):
                    e_r, e_t = np.array([x.at(meta["iteration"]) for x in explos], np.float32).T
                    t_it = time.perf_counter()
                    ts, metrics, outcome, problems = learner.iteration(ts, e_r)
                    outcome = distributed.to_host(outcome)  # Rollout of [seed, env]; waits for the device
                    if compile_s is None:
                        compile_s = time.perf_counter() - t_it
                        self.log(
                            f"compiled the iteration program in {compile_s:.1f} s (backend {jax.default_backend()})"
                        )
                    else:
                        iter_s, timed = iter_s + time.perf_counter() - t_it, timed + 1
                    metrics_acc.append(distributed.to_host(dict(metrics)))
                    outcomes.append(outcome)
                    meta["iteration"] += 1
                    if exchange is not None:  # every process draws the same choices from the same generator
                        chosen = []
                        for m in range(seeds):
                            failed = np.flatnonzero(~outcome.success[m])
                            chosen.append(failed[rng.random(len(failed)) < e_t[m]])
                        if any(len(rows) for rows in chosen):
                            exchange.submit(distributed.to_host(problems), chosen, meta)  # to_host: every process
                        ts = exchange.receive(ts, meta)
                eval_s = time.perf_counter()
                evs, vas = self._evaluate_and_select(ts, test, val, meta, epoch + 1)
                eval_s = time.perf_counter() - eval_s
                epoch_s = time.perf_counter() - t_epoch
                mean = {k: np.mean([x[k] for x in metrics_acc], axis=0) for k in metrics_acc[0]}  # [seed]
                out = jax.tree.map(lambda *x: np.concatenate(x, axis=1), *outcomes)
                e_r, e_t = np.array([x.at(meta["iteration"]) for x in explos]).T
                iter_s = max(iter_s, 1e-9)
                per_s = timed / iter_s if timed else float("nan")  # iterations per second
                rows = []
                for m in range(seeds):
                    rows.append(
                        {
                            "run_id": meta["run_id"],
                            "epoch": epoch + 1,
                            "setting": cfg.member_setting(m)[0] or None,
                            "seed": cfg.member_seed(m),
                            "iteration": meta["iteration"],
                            "rollout": "bare",  # test and validation: the network alone, no shield
                            "test": evs[m],
                            "validation": vas[m],
                            "train_success": float(out.success[m].mean()),
                            "train_collision": float(out.collision[m].mean()),
                            "return": float(mean["rollout_reward"][m]),
                            "critic_loss": float(mean["critic_loss"][m]),
                            "actor_loss": float(mean["actor_loss"][m]),
                            "bc_loss": float(mean["bc_loss"][m]),
                            "q": float(mean["q"][m]),
                            "q_filter_kept": float(mean["q_filter_kept"][m]),
                            "E_R": float(e_r[m]),
                            "E_T": float(e_t[m]),
                            "demos_received": meta["demos_received"][m],
                            "planned": meta["planned"][m],
                            "env_steps_per_s": steps_per_iter * per_s,  # all seeds together
                            "updates_per_s": seeds * cfg.updates_per_iteration * per_s,
                            "epoch_s": epoch_s,
                            "eval_s": eval_s,
                            "wall_s": time.perf_counter() - t_start,
                        }
                    )
                meta["epoch"] = epoch + 1
                meta["rng"] = rng.bit_generator.state
                meta["config"] = checkpoint.config_json(cfg)
                if (epoch + 1) % cfg.checkpoint_every == 0 or epoch + 1 == cfg.epochs:
                    checkpoint.save(self.ckpt, ts, meta)
                if main:
                    self._write_logs(log_path, writers, rows)
                epochs_run += 1
                per_epoch = (time.perf_counter() - t_start - (compile_s or 0.0)) / epochs_run
                self.log(_progress_line(cfg, rows, meta, eta_s=per_epoch * (cfg.epochs - epoch - 1)))
                last = rows
        finally:
            if exchange is not None:
                exchange.close()
            for writer in writers:
                if writer is not None:
                    writer.close()
        return self.finish(ts, last, compile_s, meta)

    def _evaluate_and_select(self, ts: TrainingState, test: Any, val: Any, meta: dict[str, Any], epoch: int):
        """Each member's bare success on the test set and the validation problems; the members whose
        validation success is at least their best so far export this epoch's policy (``meta``
        records it). Returns the two lists of summaries."""
        learner, members = self.learner, self.cfg.num_members
        actor = learner.policy_params(ts)
        ev_all = distributed.to_host(learner.evaluate(actor, ts.normalizer, test))
        va_all = distributed.to_host(learner.evaluate_q(actor, ts.normalizer, val, ts.critic))
        member = lambda tree, m: jax.tree.map(lambda x: x[m], tree)  # noqa: E731
        evs = [summarize(member(ev_all[0], m), "bare") for m in range(members)]
        vas = [summarize(member(va_all[0], m), "bare", q_start=va_all[1][m]) for m in range(members)]
        best = [m for m, va in enumerate(vas) if va["success_rate"] >= meta["best_val"][m]]
        host = self._host_policy(ts) if best else None
        for m in best:  # export the best by validation
            success = vas[m]["success_rate"]
            meta["best_val"][m], meta["best_epoch"][m] = success, epoch
            self._export(self.member_dir(m) / "policy", host, m, {"epoch": epoch, "validation_success": success})
        return evs, vas

    @staticmethod
    def _write_logs(log_path: Path, writers: list, rows: list[dict[str, Any]]) -> None:
        """One JSONL row per member, and its scalars to the member's TensorBoard writer."""
        with open(log_path, "a") as f:
            f.write("".join(json.dumps(r) + "\n" for r in rows))
        for writer, row in zip(writers, rows):
            if writer is None:
                continue
            scalars = {**{f"test/{k}": v for k, v in row["test"].items()}, **row}
            scalars.update({f"validation/{k}": v for k, v in row["validation"].items()})
            for k, v in scalars.items():
                if isinstance(v, float) and math.isfinite(v):
                    writer.add_scalar(k, v, row["epoch"])
            writer.flush()

    def finish(
        self, ts: TrainingState, last: list[dict[str, Any]], compile_s: float | None, meta: dict[str, Any]
    ) -> dict[str, Any]:
        """Exports each member's last policy beside its best (by validation), tests the best ones
        bare and shielded, distils them when ``distill.iterations`` > 0, and copies each setting's
        best seed (by validation) to ``OUT/policy`` (``OUT/SETTING/policy`` for several settings),
        its student to ``.../student/policy``."""
        cfg = self.cfg

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
                    "test": outcomes(load_policy(policy_dir), self.testset),  # the exported file, as deployed
                    "last_epoch": last[m] if last else None,
                }
            )
            ev = members[-1]["test"]
            self.log(
                f"{members[-1]['setting'] or 'seed'} {members[-1]['seed']}: exported {policy_dir} (epoch "
                f"{meta['best_epoch'][m]}, best on validation); on the test set: success {ev['bare']['success_rate']:.3f} "
                f"bare, {ev['shielded']['success_rate']:.3f} shielded; collision {ev['bare']['collision_rate']:.3f} bare; "
                f"path {_mm(ev['bare']['path_length_mm'])}"
            )
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
        final: dict[str, Any] = {"compile_s": compile_s, "seeds": members}
        if students is not None:
            final["students"] = students
        if cfg.settings:
            final["settings"] = groups
        else:
            final = {**groups[""], **final}
        write_json(self.out / "final_eval.json", final)
        return final

    def distill(self, members: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """Each member's exported policy teaches a student (``MEMBER_DIR/student``), one after another."""

        students = []
        for m, mem in enumerate(members):
            cfg = dataclasses.replace(self.cfg.distill, seed=mem["seed"])
            folder = self.member_dir(m) / "student"
            self.log(f"{mem['setting'] or 'seed'} {mem['seed']}: distilling {mem['policy']} into {folder}")
            result = distill(load_policy(mem["policy"]), folder, cfg, self.testset, mem["policy"], self.quiet)
            students.append({"setting": mem["setting"], "seed": mem["seed"], **result})
        return students

    def _tensorboard(self, folder: Path):
        try:
            from tensorboardX import SummaryWriter  # here: its import (protobuf) only for runs that log to TensorBoard
        except ImportError:  # optional: the JSONL log has everything
            return None
        return SummaryWriter(str(folder / "tb"))
