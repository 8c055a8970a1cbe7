"""A demonstration set planned by OMPL planners on all cores (what ``python -m regrasp_mjx.demos`` and a
training run without ``--demos`` build).

Problem i is the one ``RegraspEnv.reset`` draws from ``fold_in(PRNGKey(seed), i)``. Planner
processes (:class:`~regrasp_mjx.planning.pool.PlannerPool`) plan problems 0, 1, 2, ...; each plan
is written at once to ``DIR/plans/p{i:07d}.npz`` (atomically), so an interrupted run loses no
finished plan and a restart with the same arguments plans only what is missing. Solved paths are
replayed in the environment in batches and only those that succeed there count. The run ends when
``n`` have; ``DIR/demos.npz`` then holds the first ``n`` successful problems by index (format in
:mod:`regrasp_mjx.planning.episodes`) and ``DIR/meta.json`` the settings and versions.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from regrasp_mjx.core.atomic import atomic_write, dumps, write_json
from regrasp_mjx.core.config import EnvConfig, SceneConfig, TaskConfig, is_integer, is_number, require
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.planning.episodes import DemosError, make_replay, replay_paths, save_demos
from regrasp_mjx.planning.ompl_planner import PlannerConfig
from regrasp_mjx.planning.pool import PlannerPool
from regrasp_mjx.world.sampling import Episode, sample_episode
from regrasp_mjx.world.testsets import versions

ALL_FAILED = 16  # this many plans in a row failing with an error (not unsolved) stop the build


def problem_sampler(env: RegraspEnv, seed: int, batch: int = 1024):
    """``sample(indices) -> Episode`` (numpy): problem i from ``fold_in(PRNGKey(seed), i)``."""
    base = jax.random.PRNGKey(seed)

    @jax.jit
    def draw(idx):
        keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(idx)
        return jax.vmap(
            lambda k: sample_episode(k, env.config.task, env.needle_radius, env.distances, env.wire_radius)
        )(keys)

    def sample(indices: np.ndarray) -> Episode:
        indices = np.asarray(indices, np.int32)
        padded = np.concatenate([indices, np.zeros(batch - len(indices) % batch, np.int32)])[: max(batch, len(indices))]
        out = []
        for lo in range(0, len(padded), batch):
            ep, _ = draw(padded[lo : lo + batch])
            out.append(jax.tree.map(np.asarray, ep))
        cat = jax.tree.map(lambda *x: np.concatenate(x), *out)
        return jax.tree.map(lambda x: x[: len(indices)], cat)

    return sample


def _plan_path(plans: Path, i: int) -> Path:
    return plans / f"p{i:07d}.npz"


def _write_plan(plans: Path, i: int, result: dict | None, error: str) -> None:
    poses = np.zeros((0, 7)) if not result or result.get("poses") is None else np.asarray(result["poses"])
    solved = bool(result and result["solved"])
    arrays = {
        "solved": np.array(solved),
        "poses": poses,
        "plan_time_s": np.array(result["plan_time_s"] if result else np.nan),
        "error": np.array(error or (result or {}).get("error", "")),
    }
    atomic_write(_plan_path(plans, i), lambda f: np.savez(f, **arrays))


def _read_plan(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as f:
        return {"solved": bool(f["solved"]), "poses": f["poses"], "plan_time_s": float(f["plan_time_s"])}


def _differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    """The settings that differ between two nested dicts, as ``name: there -> asked`` (at most 5)."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: {a!r} there, {b!r} asked")
    return out[:5]


def build_settings(
    n: int,
    workers: int,
    planner: str,
    direction: str,
    budget_s: float,
    checker: str,
    timeout_s: float | None,
    replay_batch: int,
) -> PlannerConfig:
    """:func:`build`'s numbers checked (ConfigError) before it makes anything; the planner's config."""
    for name, value in (("n", n), ("workers", workers), ("replay_batch", replay_batch)):
        require(is_integer(value) and value >= 1, name, value, "an integer >= 1")
    require(
        timeout_s is None or (is_number(timeout_s) and timeout_s > 0),
        "timeout_s",
        timeout_s,
        "a finite number of seconds > 0, or None (3 budgets and 30 s)",
    )
    return PlannerConfig(planner=planner, direction=direction, budget_s=budget_s, checker=checker)


def build(
    n: int,
    out: str | os.PathLike,
    *,
    seed: int = 0,
    workers: int = 1,
    planner: str = "BITstar",
    direction: str = "reverse",
    budget_s: float = 10.0,
    checker: str = "mujoco",
    timeout_s: float | None = None,
    scene: SceneConfig = SceneConfig(),
    task: TaskConfig = TaskConfig(),
    replay_batch: int = 256,
    quiet: bool = False,
    env: EnvConfig | None = None,
) -> Path:
    """Plans ``n`` demonstrations into ``out`` (resumed when it holds plans of the same settings):
    problems of ``task`` from ``seed``, ``planner`` in ``direction`` with ``budget_s`` each on
    ``workers`` processes over ``checker`` (:class:`~regrasp_mjx.planning.ompl_planner.PlannerConfig`),
    each path replayed in the environment of ``scene`` and ``task`` (or the whole ``env`` where given);
    returns ``out/demos.npz``."""
    config = env if env is not None else EnvConfig(scene=scene, task=task)
    planner_cfg = build_settings(n, workers, planner, direction, budget_s, checker, timeout_s, replay_batch)
    out = Path(out)
    plans = out / "plans"
    plans.mkdir(parents=True, exist_ok=True)
    # the checker is left out of the settings a folder must match: both give the same verdicts, and a
    # folder made before the choice existed resumes with either
    planner_settings = {k: v for k, v in dataclasses.asdict(planner_cfg).items() if k != "checker"}
    settings = {"seed": seed, "planner": planner_settings, "env": dataclasses.asdict(config)}
    meta_path = out / "meta.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        differ = _differences(old.get("settings") or {}, json.loads(dumps(settings)))
        if differ:
            raise DemosError(
                f"{out} holds plans made with other settings ({'; '.join(differ)}); "
                f"use another --out or the same arguments to resume"
            )
    else:
        meta = {
            "format": "regrasp_mjx.demos",
            "settings": settings,
            "versions": versions(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        write_json(meta_path, meta)

    env = RegraspEnv(dataclasses.replace(config, check_actions=False))
    replay = make_replay(env)
    sample = problem_sampler(env, seed)
    verified: dict[int, dict] = {}
    stats = {"planned": 0, "failed": 0, "errors": 0, "replay_failed": 0, "resumed": 0}

    def verify(items: list[tuple[int, dict]]) -> None:
        if not items:
            return
        idx = np.array([i for i, _ in items])
        ok, rows = replay_paths(env, replay, sample(idx), [p["poses"] for _, p in items], batch=replay_batch)
        for (i, plan), good, row in zip(items, ok, rows):
            if good:
                verified[i] = {**row, "problem_index": i, "plan_time_s": plan["plan_time_s"]}
            else:
                stats["replay_failed"] += 1

    existing = sorted(int(p.name[1:8]) for p in plans.glob("p*.npz"))
    done = set(existing)
    stats["resumed"] = len(existing)
    verify([(i, plan) for i in existing if (plan := _read_plan(_plan_path(plans, i)))["solved"]])

    next_index, batch_cache = 0, {}
    pending: list[tuple[int, dict]] = []
    options = {"planner": dataclasses.asdict(planner_cfg), "scene": dataclasses.asdict(config.scene), "seed": seed}
    timeout = timeout_s or 3 * budget_s + 30
    t0 = time.perf_counter()
    with (
        PlannerPool(workers, options=options, timeout_s=timeout) as pool,
        tqdm(
            total=n,
            initial=min(len(verified), n),
            desc="demonstrations",
            unit="demo",
            file=sys.stdout,
            disable=quiet,
        ) as bar,
    ):
        while len(verified) < n:
            # at most one refill per pass: a "while in flight < 4 workers" loop never ended where the
            # workers finished plans as fast as this process submitted them (31 lean-checker workers on
            # 32 cores planned 142,198 problems for 9,900 demonstrations, nothing verified until the end)
            for _ in range(4 * workers - pool.in_flight):
                while next_index in done:
                    next_index += 1
                block = next_index // 1024
                if block not in batch_cache:
                    batch_cache = {block: sample(np.arange(block * 1024, block * 1024 + 1024))}
                if pool.submit(batch_cache[block].problem(next_index % 1024), payload=next_index) is None:
                    break  # the pool's queue is full: this problem goes in the next pass
                done.add(next_index)
            for r in pool.collect():
                result = r.result if r.ok else None
                _write_plan(plans, r.payload, result, r.error)
                stats["planned"] += 1
                stats["errors"] += not r.ok
                if stats["errors"] == stats["planned"] >= ALL_FAILED:  # a broken planner, not hard problems
                    raise DemosError(
                        f"the first {ALL_FAILED} plans all failed with an error, the last: "
                        f"{r.error.strip().splitlines()[-1] if r.error.strip() else 'none given'}; "
                        "check that OMPL imports (python -c 'import ompl') and the planner settings"
                    )
                if result and result["solved"]:
                    pending.append((r.payload, result))
                else:
                    stats["failed"] += 1
            if len(pending) >= replay_batch or (pending and len(verified) + len(pending) >= n):
                before = len(verified)
                verify(pending)
                pending = []
                bar.update(min(len(verified), n) - min(before, n))
                bar.set_postfix(
                    planned=stats["planned"], plan_failed=stats["failed"], replay_failed=stats["replay_failed"]
                )
            else:
                time.sleep(0.005)
    chosen = sorted(verified)[:n]
    meta = {
        "settings": settings,
        "versions": versions(),
        "n": n,
        "wall_s": round(time.perf_counter() - t0, 2),
        "problems_planned": len(done),
        "stats": stats,
    }
    path = save_demos(out / "demos.npz", [verified[i] for i in chosen], meta)
    print(dumps({"out": str(path), "demos": len(chosen), **stats, "wall_s": meta["wall_s"]}))
    return path
