"""``python -m regrasp_mjx.train``: DDPG+BC with mixed exploration, evaluation, checkpoints, export.

    python -m regrasp_mjx.train --preset smoke --out runs/smoke
    python -m regrasp_mjx.train --preset fast --exploration mixed --out runs/fast --seed 1
    python -m regrasp_mjx.train --preset paper --out runs/paper --set batch_size=512 --set env.horizon=80
    python -m regrasp_mjx.train --preset fast --out runs/fast --resume
    python -m regrasp_mjx.train --preset fast --exploration targeted --seeds 3 --out runs/targeted

Python runs only between iterations: the planner exchange (failed episodes out with probability
E_T, demonstrations in when they are ready), and per epoch the test-set evaluation, the log line,
TensorBoard and JSONL logs and an atomic checkpoint. At the end the policy is exported
(``OUT/policy/policy.npz`` + ``policy.json``) and evaluated on the test set (``OUT/final_eval.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx import distributed, gpu_memory
from regrasp_mjx.agents.ddpg_bc.config import (
    EXPLORATION,
    LEARNERS,
    PRESETS,
    TrainConfig,
    grow_with_devices,
    make_config,
)
from regrasp_mjx.agents.ddpg_bc.train import TRANSITION, Learner, TrainingState
from regrasp_mjx.atomic import atomic_write, write_json, write_text
from regrasp_mjx.config import ConfigError, parse_overrides
from regrasp_mjx.planning.episodes import DemosError, load_demos, make_replay, replay_paths
from regrasp_mjx.policy import save_policy
from regrasp_mjx.rollout import summarize
from regrasp_mjx.sampling import PAPER300, Episode, TestsetError, load_testset

VALIDATION_SEED = 1_000_003
DEFAULT_TESTSET = PAPER300


def _config_json(cfg: TrainConfig) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


# Learner fields added after checkpoints were first written; each default reproduces what those
# checkpoints ran, so a checkpoint without them resumes as if they had been saved.
_ADDED_FIELDS = ("critic_layer_norm", "bc_decay_epochs", "bc_decay_to", "action_l2_decay", "shard")


def with_added_defaults(saved: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's config with the learner fields added since filled in at their defaults."""
    defaults = _config_json(TrainConfig())
    return {**{k: defaults[k] for k in _ADDED_FIELDS if k not in saved}, **saved}


def _to_episode(problems: Any, rows: np.ndarray) -> Episode:
    take = lambda x: np.asarray(x)[rows]  # noqa: E731
    n = len(rows)
    return Episode(
        needle_pos=take(problems.needle_pos),
        needle_quat=take(problems.needle_quat),
        start_pos=take(problems.ee_pos),
        start_quat=take(problems.ee_quat),
        goal_pos=take(problems.goal_pos),
        goal_quat=take(problems.goal_quat),
        grasp=np.zeros((n, 4)),
        goal_depth=np.zeros(n),
    )


def _like(template: Any, saved: np.ndarray) -> Any:
    """A restored leaf of the template's kind: Python scalars stay Python scalars and weakly typed
    scalars stay weak, so the resumed state traces exactly like a fresh one (no recompile)."""
    if not isinstance(template, jax.Array):
        return type(template)(saved.item()) if np.ndim(saved) == 0 else np.asarray(saved)
    if template.weak_type:
        return jnp.asarray(saved.item())
    return jnp.asarray(saved, dtype=template.dtype)


def _copy_policy(src: Path, dst: Path) -> None:
    for name in ("policy.npz", "policy.json"):
        atomic_write(dst / name, lambda f, src=src / name: f.write(src.read_bytes()))


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} mm"


class Run:
    """One training run in ``out``; :meth:`train` is resumable."""

    def __init__(self, cfg: TrainConfig, out: Path, demos_dir: Path | None, testset: Path, quiet: bool = False):
        self.cfg, self.out, self.quiet = cfg, out, quiet
        self.ckpt = out / "checkpoint"
        self.testset, _ = load_testset(testset)
        # Model selection uses problems of their own (never the test set): 300 from another seed.
        from regrasp_mjx.testset import make_testset

        self.valset = make_testset(cfg.validation_size, VALIDATION_SEED + cfg.seed, cfg.env)
        self.demos = self._demos(demos_dir)
        self.learner = Learner(cfg)
        self.replay = None

    def log(self, msg: str) -> None:
        if not self.quiet and distributed.is_main():
            print(msg, flush=True)

    def _demos(self, demos_dir: Path | None):
        if demos_dir is not None:
            return load_demos(demos_dir)
        path = self.out / "demos"
        if not (path / "demos.npz").exists() and distributed.is_main():
            from regrasp_mjx import demos as demos_cli

            self.log(f"building {self.cfg.num_demos} demonstrations in {path} (BIT* reverse) ...")
            args = argparse.Namespace(
                n=self.cfg.num_demos,
                workers=self.cfg.planner_workers or max(1, (os.cpu_count() or 2) - 1),
                out=str(path),
                seed=self.cfg.seed,
                planner="BITstar",
                direction="reverse",
                budget_s=self.cfg.planner_budget_s,
                timeout_s=None,
                jaw_angle_deg=self.cfg.env.scene.jaw_angle_deg,
                replay_batch=64,
                quiet=self.quiet,
            )
            demos_cli.build(args)
        distributed.sync("demos")  # the others wait for process 0's set
        demos = load_demos(path)
        env_meta = demos.meta.get("settings", {}).get("env", {})
        if env_meta and env_meta.get("scene") != dataclasses.asdict(self.cfg.env.scene):
            raise DemosError(f"{path} was made for scene {env_meta.get('scene')}, this run uses {self.cfg.env.scene}")
        return demos

    # ---- checkpoints ------------------------------------------------------------------------
    def save(self, ts: TrainingState, meta: dict[str, Any]) -> None:
        """The whole training state (networks, optimisers, targets, normaliser, both buffers, key) as
        plain arrays in tree order, then the metadata; each file written atomically, state first."""
        leaves = distributed.to_host(jax.tree_util.tree_leaves(ts))  # a collective: every process
        if not distributed.is_main():
            return
        arrays = {f"leaf_{i:05d}": np.asarray(x) for i, x in enumerate(leaves)}
        atomic_write(self.ckpt / "state.npz", lambda f: np.savez(f, **arrays))
        write_json(self.ckpt / "meta.json", meta, indent=None)

    def load(self, template: TrainingState) -> tuple[TrainingState, dict[str, Any]]:
        meta_path, state_path = self.ckpt / "meta.json", self.ckpt / "state.npz"
        if not (meta_path.is_file() and state_path.is_file()):
            raise ConfigError(f"--resume: no checkpoint in {self.ckpt}")
        meta = json.loads(meta_path.read_text())
        saved, now = with_added_defaults(meta["config"]), _config_json(self.cfg)
        saved.pop("epochs", None)
        now.pop("epochs", None)
        if saved != now:
            diff = sorted(k for k in now if saved.get(k) != now[k])
            raise ConfigError(
                f"--resume: the checkpoint in {self.ckpt} was made with other settings ({diff}); "
                "resume with the same preset, exploration and overrides (epochs may grow)"
            )
        leaves, treedef = jax.tree_util.tree_flatten(template)
        try:
            with np.load(state_path, allow_pickle=False) as f:
                saved_leaves = [f[f"leaf_{i:05d}"] for i in range(len(leaves))]
                extra = len(f.files) - len(leaves)
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
            "config": _config_json(cfg),
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
            ts, meta = self.load(ts)
            ts = learner.place(ts)
            self.log(f"resumed from {self.ckpt} at epoch {meta['epoch']}")
            self._truncate_log(meta["epoch"])
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        # numpy, not device arrays: in a distributed run a host value given to a jitted program is
        # the same on every process and is placed on the global mesh as such
        test = jax.tree.map(lambda x: np.asarray(x, np.float32), self.testset)
        val = jax.tree.map(lambda x: np.asarray(x, np.float32), self.valset)
        explos = [cfg.member_setting(m)[1] for m in range(seeds)]
        targeted = any(x.targeted_eps > 0 for x in explos)
        pool = self._pool() if targeted and distributed.is_main() else None  # planners: process 0's
        pending = [{k: [] for k in TRANSITION} for _ in range(seeds)]
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
                    outcome = distributed.to_host(outcome)  # [seed, env, 5]; waits for the device
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
                    if targeted:  # every process draws the same choices from the same generator
                        chosen = []
                        for m in range(seeds):
                            failed = np.flatnonzero(outcome[m, :, 1] == 0)
                            chosen.append(failed[rng.random(len(failed)) < e_t[m]])
                        if any(len(rows) for rows in chosen):
                            problems = distributed.to_host(problems)  # a collective: every process
                            if pool is not None:
                                self._submit(pool, problems, chosen, meta)
                        ts = self._receive(pool, ts, pending, meta)
                eval_s = time.perf_counter()
                actor = learner.policy_params(ts)
                ev_all = distributed.to_host(learner.evaluate(actor, ts.normalizer, test))
                va_all = distributed.to_host(learner.evaluate_q(actor, ts.normalizer, val, ts.critic))
                evs = [summarize({k: v[m] for k, v in ev_all.items()}, "bare") for m in range(seeds)]
                vas = [summarize({k: v[m] for k, v in va_all.items()}, "bare") for m in range(seeds)]
                best = [m for m, va in enumerate(vas) if va["success_rate"] >= meta["best_val"][m]]
                host = self._host_policy(ts) if best else None
                for m in best:  # export the best by validation
                    va = vas[m]
                    meta["best_val"][m], meta["best_epoch"][m] = va["success_rate"], epoch + 1
                    training = {"epoch": epoch + 1, "validation_success": va["success_rate"]}
                    self._export(self.member_dir(m) / "policy", host, m, training)
                eval_s = time.perf_counter() - eval_s
                epoch_s = time.perf_counter() - t_epoch
                mean = {k: np.mean([x[k] for x in metrics_acc], axis=0) for k in metrics_acc[0]}  # [seed]
                out = np.concatenate(outcomes, axis=1)
                e_r, e_t = np.array([x.at(meta["iteration"]) for x in explos]).T
                iter_s = max(iter_s, 1e-9)
                per_s = timed / iter_s if timed else float("nan")  # iterations per second
                rows = []
                for m in range(seeds):
                    rows.append(
                        {
                            "epoch": epoch + 1,
                            "setting": cfg.member_setting(m)[0] or None,
                            "seed": cfg.member_seed(m),
                            "iteration": meta["iteration"],
                            "rollout": "bare",  # test and validation: the network alone, no shield
                            "test": evs[m],
                            "validation": vas[m],
                            "train_success": float(out[m, :, 1].mean()),
                            "train_collision": float(out[m, :, 2].mean()),
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
                meta["config"] = _config_json(cfg)
                if (epoch + 1) % cfg.checkpoint_every == 0 or epoch + 1 == cfg.epochs:
                    self.save(ts, meta)
                if main:
                    with open(log_path, "a") as f:
                        f.write("".join(json.dumps(r) + "\n" for r in rows))
                for writer, row in zip(writers, rows):
                    if writer is None:
                        continue
                    scalars = {**{f"test/{k}": v for k, v in row["test"].items()}, **row}
                    scalars.update({f"validation/{k}": v for k, v in row["validation"].items()})
                    for k, v in scalars.items():
                        if isinstance(v, float) and math.isfinite(v):
                            writer.add_scalar(k, v, epoch + 1)
                    writer.flush()
                epochs_run += 1
                per_epoch = (time.perf_counter() - t_start - (compile_s or 0.0)) / epochs_run
                eta = per_epoch * (cfg.epochs - epoch - 1)
                each = lambda xs, f="{:.3f}": "/".join(f.format(x) for x in xs)  # noqa: E731
                r0 = rows[0]
                self.log(
                    f"epoch {epoch + 1}/{cfg.epochs}  val success {each(v['success_rate'] for v in vas)}  "
                    f"test success {each(e['success_rate'] for e in evs)} "
                    f"(collision {each(e['collision_rate'] for e in evs)}, path {'/'.join(_mm(e['path_length_mm']) for e in evs)})  "
                    f"return {each((r['return'] for r in rows), '{:+.3f}')}  critic {each((r['critic_loss'] for r in rows), '{:.4f}')}  "
                    f"actor {each((r['actor_loss'] for r in rows), '{:+.5f}')}  Q {each((r['q'] for r in rows), '{:+.3f}')}  "
                    f"E_R {each(e_r)}  E_T {each(e_t)}  demos+ {each(meta['demos_received'], '{}')}  "
                    f"{r0['env_steps_per_s']:,.0f} env-steps/s  {r0['updates_per_s']:,.0f} updates/s  "
                    f"ETA {eta / 60:.1f} min"
                )
                last = rows
        finally:
            if pool is not None:
                pool.close()
            for writer in writers:
                if writer is not None:
                    writer.close()
        return self.finish(ts, last, compile_s, meta)

    def finish(
        self, ts: TrainingState, last: list[dict[str, Any]], compile_s: float | None, meta: dict[str, Any]
    ) -> dict[str, Any]:
        """Exports each member's last policy beside its best (by validation), tests the best ones
        bare and shielded, distils them when ``distill.iterations`` > 0, and copies each setting's
        best seed (by validation) to ``OUT/policy`` (``OUT/SETTING/policy`` for several settings),
        its student to ``.../student/policy``."""
        cfg = self.cfg
        from regrasp_mjx.evaluate import outcomes
        from regrasp_mjx.policy import load_policy

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
        from regrasp_mjx.distill import distill
        from regrasp_mjx.policy import load_policy

        students = []
        for m, mem in enumerate(members):
            cfg = dataclasses.replace(self.cfg.distill, seed=mem["seed"])
            folder = self.member_dir(m) / "student"
            self.log(f"{mem['setting'] or 'seed'} {mem['seed']}: distilling {mem['policy']} into {folder}")
            result = distill(load_policy(mem["policy"]), folder, cfg, self.testset, mem["policy"], self.quiet)
            students.append({"setting": mem["setting"], "seed": mem["seed"], **result})
        return students

    # ---- the planner exchange ---------------------------------------------------------------
    def _pool(self):
        from regrasp_mjx.planning.ompl_planner import PlannerConfig
        from regrasp_mjx.planning.pool import PlannerPool

        planner = PlannerConfig(planner="BITstar", direction="reverse", budget_s=self.cfg.planner_budget_s)
        options = {
            "planner": dataclasses.asdict(planner),
            "scene": dataclasses.asdict(self.cfg.env.scene),
            "seed": self.cfg.seed,
        }
        workers = self.cfg.planner_workers or max(1, (os.cpu_count() or 2) - 1)
        return PlannerPool(
            workers, options=options, queue_size=self.cfg.planner_queue, timeout_s=3 * self.cfg.planner_budget_s + 30
        )

    def _submit(self, pool, problems, chosen: list[np.ndarray], meta: dict[str, Any]) -> None:
        """Sends the chosen failed episodes of every seed to the pool, taking the seeds in turn so
        that a full queue is shared fairly; stops at a full queue (the learner never waits)."""
        if not any(len(rows) for rows in chosen):
            return
        problems = jax.device_get(problems)
        episodes = [_to_episode(jax.tree.map(lambda x, m=m: x[m], problems), rows) for m, rows in enumerate(chosen)]
        for j in range(max(len(rows) for rows in chosen)):
            for m, ep in enumerate(episodes):
                if j >= len(chosen[m]):
                    continue
                job = pool.submit(
                    {
                        "needle": np.r_[ep.needle_pos[j], ep.needle_quat[j]],
                        "start": np.r_[ep.start_pos[j], ep.start_quat[j]],
                        "goal": np.r_[ep.goal_pos[j], ep.goal_quat[j]],
                    },
                    payload=(m, jax.tree.map(lambda x, j=j: x[j], ep)),
                )
                if job is None:
                    return
                meta["planned"][m] += 1

    def _receive(self, pool, ts: TrainingState, pending: list[dict[str, list[np.ndarray]]], meta: dict[str, Any]):
        """Inserts the planner demonstrations that fill a ``demo_chunk`` into their seed's online
        buffer. The pool is process 0's; in a distributed run its chunks are broadcast, so every
        process inserts the same ones."""
        chunks = self._ready_chunks(pool, pending, meta) if pool is not None else []
        if distributed.multi_process():
            chunks = self._broadcast_chunks(chunks)
        for m, data in chunks:
            ts = self.learner.add_online(ts, np.int32(m), data)
        return ts

    def _ready_chunks(self, pool, pending, meta) -> list[tuple[int, dict[str, np.ndarray]]]:
        done = [r for r in pool.collect() if r.ok and r.result["solved"]]
        if done:
            if self.replay is None:
                self.replay = make_replay(self.learner.env)
            eps = jax.tree.map(lambda *x: np.stack(x), *[r.payload[1] for r in done])
            ok, rows = replay_paths(self.learner.env, self.replay, eps, [r.result["poses"] for r in done], batch=64)
            for r, good, row in zip(done, ok, rows):
                if good:
                    m = r.payload[0]
                    meta["demos_received"][m] += 1
                    for k in ("obs", "action", "reward", "next_obs"):
                        pending[m][k].append(row[k])
                    pending[m]["terminal"].append(row["done"])
        chunk, chunks = self.cfg.demo_chunk, []
        for m, waiting in enumerate(pending):
            while sum(len(x) for x in waiting["obs"]) >= chunk:
                cat = {k: np.concatenate(v) for k, v in waiting.items()}
                chunks.append((m, {k: np.asarray(v[:chunk], np.float32) for k, v in cat.items()}))
                for k in waiting:
                    waiting[k] = [cat[k][chunk:]] if len(cat[k]) > chunk else []
        return chunks

    def _broadcast_chunks(self, chunks: list[tuple[int, dict[str, np.ndarray]]]):
        """Process 0's ``chunks`` on every process: their count first, then the stacked arrays."""
        n = int(distributed.broadcast(np.int32(len(chunks))))
        if n == 0:
            return []
        size, env = self.cfg.demo_chunk, self.learner.env
        obs, act = env.observation_size, env.action_size
        shapes = {"obs": (obs,), "action": (act,), "reward": (), "next_obs": (obs,), "terminal": ()}
        if chunks:
            stacked = {k: np.stack([c[1][k] for c in chunks]) for k in TRANSITION}
            members = np.array([c[0] for c in chunks], np.int32)
        else:
            stacked = {k: np.zeros((n, size, *shapes[k]), np.float32) for k in TRANSITION}
            members = np.zeros(n, np.int32)
        members, stacked = distributed.broadcast((members, stacked))
        return [(int(members[i]), {k: v[i] for k, v in stacked.items()}) for i in range(n)]

    def _tensorboard(self, folder: Path):
        try:
            from tensorboardX import SummaryWriter
        except ImportError:  # optional: the JSONL log has everything
            return None
        return SummaryWriter(str(folder / "tb"))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.train", description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="smoke", choices=sorted(PRESETS), help="scale preset (default smoke)")
    p.add_argument(
        "--exploration",
        default="mixed",
        help=f"Table I setting, one of {', '.join(sorted(EXPLORATION))} (default mixed); several, comma-separated, "
        "train side by side in one program (OUT/SETTING/seedS)",
    )
    p.add_argument(
        "--learner",
        default="ours",
        choices=LEARNERS,
        help="ours (default: Gaussian exploration floor, twin critics, target smoothing, actor EMA, cosine LR) "
        "or paper (SPEC's DDPG+BC as the paper ran it)",
    )
    p.add_argument("--out", required=True, help="run folder: logs, checkpoint, demos, exported policy")
    p.add_argument("--seed", type=int, default=None, help="PRNG seed (default: the preset's, 0)")
    p.add_argument("--seeds", type=int, default=None, help="train seeds SEED..SEED+N-1 together as one vmapped program")
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        help="use this many local GPUs (0 = all; default 1), shared as --shard says",
    )
    p.add_argument(
        "--shard",
        default=None,
        choices=("auto", "members", "envs"),
        help="members: whole seeds/settings per GPU, no communication; envs: data parallel (environments, "
        "buffer and batches split, gradients averaged); auto (default): members when they divide evenly",
    )
    p.add_argument(
        "--grow-batch",
        action="store_true",
        help="data parallel with weak scaling: the preset's environments, batch, buffer and demo chunk are "
        "each GPU's share (global sizes grow with --devices) and both learning rates scale by sqrt(devices)",
    )
    p.add_argument(
        "--gpu-memory",
        default=None,
        metavar="FRACTION|grow",
        help="share of the GPU to pre-allocate (e.g. 0.45 for each of two runs on one GPU) or 'grow' "
        "(allocate as needed); default: JAX's 75 %%, or 'grow' when another process runs on the GPU",
    )
    p.add_argument(
        "--distributed",
        action="store_true",
        help="join a run of several processes (hosts) through jax.distributed: the coordinator, process "
        "count and index come from the flags below or are detected (SLURM, Open MPI, JAX_COORDINATOR_ADDRESS)",
    )
    p.add_argument(
        "--coordinator", default=None, metavar="HOST:PORT", help="process 0's address (implies --distributed)"
    )
    p.add_argument("--num-processes", type=int, default=None, help="processes in the run (with --coordinator)")
    p.add_argument("--process-id", type=int, default=None, help="this process's index, 0..N-1 (with --coordinator)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint")
    p.add_argument("--demos", default=None, help="a demonstration folder (default: build OUT/demos)")
    p.add_argument("--testset", default=str(DEFAULT_TESTSET), help="evaluation test set (.npz)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field, dotted for nested ones (repeatable)",
    )
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    try:
        overrides = parse_overrides(args.set)
        if args.seed is not None:
            overrides["seed"] = args.seed
        if args.seeds is not None:
            overrides["num_seeds"] = args.seeds
        if args.devices is not None:
            overrides["devices"] = args.devices
        if args.shard is not None:
            overrides["shard"] = args.shard
        cfg = make_config(args.preset, args.exploration, args.learner, **overrides)
        gpu_memory.configure(gpu_memory.parse_setting(args.gpu_memory))  # before JAX starts a GPU client
        if args.distributed or args.coordinator:
            distributed.initialize(args.coordinator, args.num_processes, args.process_id)
        if args.grow_batch:
            cfg = grow_with_devices(cfg, cfg.devices or len(jax.devices()))
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        if jax.default_backend() == "cpu" and args.preset != "smoke":
            warnings.warn("training on the CPU: no GPU is visible to JAX; this preset expects one", stacklevel=1)
        cache = Path(os.environ.get("REGRASP_JAX_CACHE", Path.home() / ".cache" / "regrasp_mjx" / "jax"))
        jax.config.update("jax_compilation_cache_dir", str(cache))
        run = Run(cfg, out, Path(args.demos) if args.demos else None, Path(args.testset), args.quiet)
        final = run.train(resume=args.resume)
    except (ConfigError, DemosError, TestsetError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except jax.errors.JaxRuntimeError as err:
        if not gpu_memory.is_out_of_memory(err):
            raise
        print(f"error: {gpu_memory.out_of_memory_message(cfg)}\n({str(err).splitlines()[0]})", file=sys.stderr)
        return 3

    def summary(g: dict[str, Any]) -> dict[str, Any]:
        out = {"policy": g["policy"], "test": g["test"]}
        if "student" in g:
            out["student"] = {"policy": g["student"]["student"], "test": g["student"]["test"]}
        return out

    if not distributed.is_main():
        return 0  # process 0 reports
    if "settings" in final:
        print(json.dumps({"out": str(out), "settings": {k: summary(g) for k, g in final["settings"].items()}}))
    else:
        print(json.dumps({"out": str(out), **summary(final)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
