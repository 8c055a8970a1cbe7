"""``python -m regrasp_mjx.train``: DDPG+BC with mixed exploration, evaluation, checkpoints, export.

    python -m regrasp_mjx.train --preset smoke --out runs/smoke
    python -m regrasp_mjx.train --preset fast --exploration mixed --out runs/fast --seed 1
    python -m regrasp_mjx.train --preset paper --out runs/paper --set batch_size=512 --set env.horizon=80
    python -m regrasp_mjx.train --preset fast --out runs/fast --resume

Python runs only between iterations: the planner exchange (failed episodes out with probability
E_T, demonstrations in when they are ready), and per epoch the test-set evaluation, the log line,
TensorBoard and JSONL logs and an atomic checkpoint. At the end the policy is exported
(``OUT/policy/policy.npz`` + ``policy.json``) and evaluated on the test set (``OUT/final_eval.json``).
"""

from __future__ import annotations

import argparse
import ast
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

from regrasp_mjx.agents.ddpg_bc.config import EXPLORATION, PRESETS, TrainConfig, make_config
from regrasp_mjx.agents.ddpg_bc.train import TRANSITION, Learner, TrainingState
from regrasp_mjx.config import ConfigError
from regrasp_mjx.planning.episodes import DemosError, _atomic_write, load_demos, make_replay, replay_paths
from regrasp_mjx.policy import save_policy
from regrasp_mjx.sampling import Episode, TestsetError, load_testset

VALIDATION_SEED = 1_000_003
DEFAULT_TESTSET = Path(__file__).resolve().parent.parent / "experiments" / "testsets" / "paper300.npz"


def _parse_overrides(items: list[str]) -> dict[str, Any]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r} is not accepted: KEY=VALUE, e.g. --set env.horizon=80")
        try:
            out[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            out[key.strip()] = value.strip()
    return out


def _config_json(cfg: TrainConfig) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


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


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} mm"


def summarize_eval(result: dict[str, Any]) -> dict[str, float]:
    r = {k: np.asarray(v) for k, v in result.items()}
    ok = r["success"] > 0
    return {
        "success_rate": float(ok.mean()),
        "collision_rate": float(r["collision"].mean()),
        "time_out_rate": float(r["time_out"].mean()),
        "path_length_mm": float(r["path_length_mm"][ok].mean()) if ok.any() else None,
        "steps": float(r["steps"][ok].mean()) if ok.any() else None,
    }


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
        if not self.quiet:
            print(msg, flush=True)

    def _demos(self, demos_dir: Path | None):
        if demos_dir is not None:
            return load_demos(demos_dir)
        path = self.out / "demos"
        if not (path / "demos.npz").exists():
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
        demos = load_demos(path)
        env_meta = demos.meta.get("settings", {}).get("env", {})
        if env_meta and env_meta.get("scene") != dataclasses.asdict(self.cfg.env.scene):
            raise DemosError(f"{path} was made for scene {env_meta.get('scene')}, this run uses {self.cfg.env.scene}")
        return demos

    # ---- checkpoints ------------------------------------------------------------------------
    def save(self, ts: TrainingState, meta: dict[str, Any]) -> None:
        """The whole training state (networks, optimisers, targets, normaliser, both buffers, key) as
        plain arrays in tree order, then the metadata; each file written atomically, state first."""
        leaves = jax.device_get(jax.tree_util.tree_leaves(ts))
        arrays = {f"leaf_{i:05d}": np.asarray(x) for i, x in enumerate(leaves)}
        _atomic_write(self.ckpt / "state.npz", lambda f: np.savez(f, **arrays))
        _atomic_write(self.ckpt / "meta.json", lambda f: f.write(json.dumps(meta).encode()))

    def load(self, template: TrainingState) -> tuple[TrainingState, dict[str, Any]]:
        meta_path, state_path = self.ckpt / "meta.json", self.ckpt / "state.npz"
        if not (meta_path.is_file() and state_path.is_file()):
            raise ConfigError(f"--resume: no checkpoint in {self.ckpt}")
        meta = json.loads(meta_path.read_text())
        saved, now = meta["config"], _config_json(self.cfg)
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
    def train(self, resume: bool = False) -> dict[str, Any]:
        cfg, learner = self.cfg, self.learner
        demos = {k: jnp.asarray(getattr(self.demos, k)) for k in ("obs", "action", "reward", "next_obs")}
        demos["terminal"] = jnp.asarray(self.demos.done)
        ts = learner.init(jax.random.PRNGKey(cfg.seed), demos)
        meta: dict[str, Any] = {
            "epoch": 0,
            "iteration": 0,
            "demos_received": 0,
            "planned": 0,
            "rng": np.random.default_rng(cfg.seed).bit_generator.state,
        }
        if resume:
            ts, meta = self.load(ts)
            self.log(f"resumed from {self.ckpt} at epoch {meta['epoch']}")
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        test = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), self.testset)
        val = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), self.valset)
        explo = cfg.exploration
        pool = self._pool() if explo.targeted_eps > 0 else None
        pending: dict[str, list[np.ndarray]] = {k: [] for k in TRANSITION}
        log_path = self.out / "log.jsonl"
        writer = self._tensorboard()
        steps_per_iter = cfg.num_envs * cfg.env.horizon
        t_start, compile_s, last, epochs_run = time.perf_counter(), None, {}, 0
        try:
            for epoch in range(meta["epoch"], cfg.epochs):
                t_epoch = time.perf_counter()
                metrics_acc: list[dict[str, float]] = []
                outcomes = []
                iter_s, timed = 0.0, 0
                for _ in range(cfg.iterations_per_epoch):
                    e_r, e_t = explo.at(meta["iteration"])
                    t_it = time.perf_counter()
                    ts, metrics, outcome, problems = learner.iteration(ts, jnp.float32(e_r))
                    outcome = np.asarray(outcome)  # waits for the device
                    if compile_s is None:
                        compile_s = time.perf_counter() - t_it
                        self.log(
                            f"compiled the iteration program in {compile_s:.1f} s (backend {jax.default_backend()})"
                        )
                    else:
                        iter_s, timed = iter_s + time.perf_counter() - t_it, timed + 1
                    metrics_acc.append({k: float(v) for k, v in metrics.items()})
                    outcomes.append(outcome)
                    meta["iteration"] += 1
                    if pool is not None:
                        failed = np.flatnonzero(outcome[:, 1] == 0)
                        chosen = failed[rng.random(len(failed)) < e_t]
                        self._submit(pool, problems, chosen, meta)
                        ts = self._receive(pool, ts, pending, meta)
                eval_s = time.perf_counter()
                ev = summarize_eval(learner.evaluate(ts.actor, ts.normalizer, test))
                va = summarize_eval(learner.evaluate(ts.actor, ts.normalizer, val))
                if va["success_rate"] >= meta.get("best_val", -1.0):  # export the best by validation
                    meta["best_val"], meta["best_epoch"] = va["success_rate"], epoch + 1
                    save_policy(
                        self.out / "policy",
                        ts.actor,
                        ts.normalizer,
                        cfg.hidden,
                        cfg.env,
                        extra={
                            "training": {
                                "config": _config_json(cfg),
                                "epoch": epoch + 1,
                                "validation_success": va["success_rate"],
                            }
                        },
                    )
                eval_s = time.perf_counter() - eval_s
                epoch_s = time.perf_counter() - t_epoch
                mean = {k: float(np.mean([m[k] for m in metrics_acc])) for k in metrics_acc[0]}
                out = np.concatenate(outcomes)
                e_r, e_t = explo.at(meta["iteration"])
                iter_s = max(iter_s, 1e-9)
                row = {
                    "epoch": epoch + 1,
                    "iteration": meta["iteration"],
                    "test": ev,
                    "train_success": float(out[:, 1].mean()),
                    "train_collision": float(out[:, 2].mean()),
                    "return": mean["rollout_reward"],
                    "critic_loss": mean["critic_loss"],
                    "actor_loss": mean["actor_loss"],
                    "bc_loss": mean["bc_loss"],
                    "q": mean["q"],
                    "q_filter_kept": mean["q_filter_kept"],
                    "E_R": e_r,
                    "E_T": e_t,
                    "demos_received": meta["demos_received"],
                    "planned": meta["planned"],
                    "env_steps_per_s": steps_per_iter * timed / iter_s if timed else float("nan"),
                    "updates_per_s": cfg.updates_per_iteration * timed / iter_s if timed else float("nan"),
                    "epoch_s": epoch_s,
                    "eval_s": eval_s,
                    "wall_s": time.perf_counter() - t_start,
                }
                meta["epoch"] = epoch + 1
                meta["rng"] = rng.bit_generator.state
                meta["config"] = _config_json(cfg)
                self.save(ts, meta)
                with open(log_path, "a") as f:
                    f.write(json.dumps(row) + "\n")
                if writer is not None:
                    for k, v in {
                        **{f"test/{k}": v for k, v in ev.items()},
                        **{k: v for k, v in row.items() if isinstance(v, float)},
                    }.items():
                        if v is not None and math.isfinite(v):
                            writer.add_scalar(k, v, epoch + 1)
                    writer.flush()
                epochs_run += 1
                per_epoch = (time.perf_counter() - t_start - (compile_s or 0.0)) / epochs_run
                eta = per_epoch * (cfg.epochs - epoch - 1)
                self.log(
                    f"epoch {epoch + 1}/{cfg.epochs}  val success {va['success_rate']:.3f}  test success {ev['success_rate']:.3f} "
                    f"(collision {ev['collision_rate']:.3f}, path {_mm(ev['path_length_mm'])})  "
                    f"return {row['return']:+.3f}  critic {row['critic_loss']:.4f}  actor {row['actor_loss']:+.5f}  "
                    f"Q {row['q']:+.3f}  E_R {e_r:.3f}  E_T {e_t:.3f}  demos+ {meta['demos_received']}  "
                    f"{row['env_steps_per_s']:,.0f} env-steps/s  {row['updates_per_s']:,.0f} updates/s  "
                    f"ETA {eta / 60:.1f} min"
                )
                last = row
        finally:
            if pool is not None:
                pool.close()
            if writer is not None:
                writer.close()
        return self.finish(ts, last, compile_s, meta)

    def finish(
        self, ts: TrainingState, last: dict[str, Any], compile_s: float | None, meta: dict[str, Any]
    ) -> dict[str, Any]:
        """Exports the last policy beside the best one (by validation) and tests the best."""
        cfg = self.cfg
        save_policy(
            self.out / "policy_last",
            ts.actor,
            ts.normalizer,
            cfg.hidden,
            cfg.env,
            extra={"training": {"config": _config_json(cfg), "epoch": cfg.epochs}},
        )
        from regrasp_mjx.policy import load_policy

        policy_dir = self.out / "policy"
        policy = load_policy(policy_dir)
        test = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), self.testset)
        ev = summarize_eval(self.learner.evaluate(policy.actor_params, policy.normalizer, test))
        final = {
            "policy": str(policy_dir),
            "best_epoch": meta.get("best_epoch"),
            "best_validation_success": meta.get("best_val"),
            "test": ev,
            "compile_s": compile_s,
            "last_epoch": last,
        }
        _atomic_write(self.out / "final_eval.json", lambda f: f.write(json.dumps(final, indent=2).encode()))
        self.log(
            f"exported {policy_dir} (epoch {meta.get('best_epoch')}, best on validation); on the test set: "
            f"success {ev['success_rate']:.3f}, collision {ev['collision_rate']:.3f}, path {_mm(ev['path_length_mm'])}"
        )
        return final

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

    def _submit(self, pool, problems, rows: np.ndarray, meta: dict[str, Any]) -> None:
        if len(rows) == 0:
            return
        ep = _to_episode(problems, rows)
        for j in range(len(rows)):
            job = pool.submit(
                {
                    "needle": np.r_[ep.needle_pos[j], ep.needle_quat[j]],
                    "start": np.r_[ep.start_pos[j], ep.start_quat[j]],
                    "goal": np.r_[ep.goal_pos[j], ep.goal_quat[j]],
                },
                payload=jax.tree.map(lambda x, j=j: x[j], ep),
            )
            if job is None:  # queue full: the learner never waits
                break
            meta["planned"] += 1

    def _receive(self, pool, ts: TrainingState, pending: dict[str, list[np.ndarray]], meta: dict[str, Any]):
        done = [r for r in pool.collect() if r.ok and r.result["solved"]]
        if done:
            if self.replay is None:
                self.replay = make_replay(self.learner.env)
            eps = jax.tree.map(lambda *x: np.stack(x), *[r.payload for r in done])
            ok, rows = replay_paths(self.learner.env, self.replay, eps, [r.result["poses"] for r in done], batch=64)
            for good, row in zip(ok, rows):
                if good:
                    meta["demos_received"] += 1
                    for k in ("obs", "action", "reward", "next_obs"):
                        pending[k].append(row[k])
                    pending["terminal"].append(row["done"])
        chunk = self.cfg.demo_chunk
        while sum(len(x) for x in pending["obs"]) >= chunk:
            cat = {k: np.concatenate(v) for k, v in pending.items()}
            ts = self.learner.add_online(ts, {k: jnp.asarray(v[:chunk], jnp.float32) for k, v in cat.items()})
            for k in pending:
                pending[k] = [cat[k][chunk:]] if len(cat[k]) > chunk else []
        return ts

    def _tensorboard(self):
        try:
            from tensorboardX import SummaryWriter
        except ImportError:  # optional: the JSONL log has everything
            return None
        return SummaryWriter(str(self.out / "tb"))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.train", description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="smoke", choices=sorted(PRESETS), help="scale preset (default smoke)")
    p.add_argument(
        "--exploration", default="mixed", choices=sorted(EXPLORATION), help="Table I setting (default mixed)"
    )
    p.add_argument("--out", required=True, help="run folder: logs, checkpoint, demos, exported policy")
    p.add_argument("--seed", type=int, default=None, help="PRNG seed (default: the preset's, 0)")
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
        overrides = _parse_overrides(args.set)
        if args.seed is not None:
            overrides["seed"] = args.seed
        cfg = make_config(args.preset, args.exploration, **overrides)
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
    print(json.dumps({"out": str(out), "test": final["test"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
