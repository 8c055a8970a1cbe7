"""A policy's plans of test-set problems: each row planned through ``Policy.plan`` on its own
needle, the outcomes bare and shielded, the numbers ``python -m regrasp_mjx.evaluate`` prints
(:func:`evaluate`: rates, planning time, throughput), and the two engines of ``Policy.plan`` (lean
CPU, JAX) compared problem by problem (``python -m regrasp_mjx.evaluate --agreement``)."""

from __future__ import annotations

import time

import jax
import numpy as np

from regrasp_mjx.envs.rollout import summarize
from regrasp_mjx.inference.jaw_opening import opening_steps
from regrasp_mjx.inference.plans import NO_LIBRARY, auto_engine
from regrasp_mjx.inference.queries import far_starts
from regrasp_mjx.world.sampling import episode_needles, episode_poses

VERDICTS = ("start_valid", "success", "collision", "time_out", "steps")  # what a plan decides


def plan_testset(policy, episodes, shield: bool):
    """Test-set rows planned through ``Policy.plan`` (each with its own needle): one batched
    ``Plan`` (a colliding start counts as a collision)."""
    return policy.plan(*episode_poses(episodes), check_grasp=False, shield=shield, **episode_needles(episodes))


def outcomes(policy, episodes) -> dict[str, dict]:
    """A loaded policy planned on the problems through ``Policy.plan``, bare and shielded."""
    return {
        name: summarize(plan_testset(policy, episodes, shield), name)
        for name, shield in (("bare", False), ("shielded", True))
    }


def engine_agreement(policy, episodes, shield: bool = True) -> dict:
    """Each problem planned one at a time on the lean CPU path and all at once on the JAX path
    (``Policy.plan``'s two engines), compared: ``batch`` (the JAX path's ``Plan``), ``differ``
    (``(row, field)`` where a verdict or a trajectory's length differs, or, for a policy whose jaws
    open on the way, the step they opened before: ``opened_at``, then also the JAX plans' ``[N]``, -1
    never), and per problem ``[N]`` the largest difference in an action (``action_diff``) and a pose
    (``pose_diff``), the path lengths' difference (``path_diff_mm``), ``steps`` and ``time_out``."""
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes)  # each problem on its own needle, as plan_testset plans them
    batch = policy.plan(needle, start, goal, check_grasp=False, shield=shield, engine="jax", **needles)
    out = {
        "batch": batch,
        "differ": [],
        **{k: np.zeros(len(needle)) for k in ("action_diff", "pose_diff", "path_diff_mm")},
    }
    opens = policy.env_config.jaw_open_deg is not None
    if opens:  # the step each JAX plan's jaws opened before, as the environment found it, and the lean rollout's
        radii = np.stack([needles["needle_radius_mm"], needles["wire_radius_mm"]], 1) * 1e-3
        out["opened_at"] = opening_steps(policy, needle, batch.poses, batch.steps, radii)
    for i in range(len(needle)):
        kw = {k: v[i] for k, v in needles.items()}
        one = policy.plan(needle[i], start[i], goal[i], check_grasp=False, shield=shield, engine="lean", **kw)
        out["differ"] += [(i, f) for f in VERDICTS if getattr(one, f) != getattr(batch, f)[i]]
        if opens:
            task = policy.task_ranges.keywords_vector(kw)
            lean = policy.lean(shield)(needle[i], start[i], goal[i], task, NO_LIBRARY)
            out["differ"] += [(i, "opened_at")] if lean.opened_at != out["opened_at"][i] else []
        n = int(one.steps)  # one query's trajectory is its own; the batch's runs on to its longest plan
        if (i, "steps") in out["differ"] or one.poses.shape != (n + 1, 7) or one.actions.shape != (n, 6):
            out["differ"] += [(i, "trajectory")]
            continue
        out["action_diff"][i] = float(np.abs(one.actions - batch.actions[i, :n]).max()) if n else 0.0
        out["pose_diff"][i] = float(np.abs(one.poses - batch.poses[i, : n + 1]).max())
        out["path_diff_mm"][i] = abs(float(one.path_length_mm) - float(batch.path_length_mm[i]))
    return {**out, "steps": np.asarray(batch.steps), "time_out": np.asarray(batch.time_out, bool)}


# the most queries one batched call plans: larger --batch-size values run as equal chunks of at most
# this many, one after the other (65,536 shielded queries fit one H100 with room to spare,
# docs/results.md; a million at once ran out of memory on a 2-core machine, issue 46)
BATCH_CHUNK = 65536


def evaluate(
    policy,
    episodes,
    timed_queries: int | None = None,
    batch_repeats: int = 5,
    batch_size: int | None = None,
    shield: bool = True,
) -> dict:
    """The numbers of one policy on one test set (see the module docstring). The throughput batch
    repeats the test set's queries up to ``batch_size``; ``timed_queries=0`` and
    ``batch_repeats=0`` skip the timings."""
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes)
    n = len(needle)

    def run(needle, start, goal, rows=slice(None)):
        kw = {k: v[rows] for k, v in needles.items()}
        return policy.plan(needle, start, goal, check_grasp=False, shield=shield, **kw)

    plan = run(needle, start, goal)
    size = batch_size or n
    # a batch larger than BATCH_CHUNK runs as equal chunks of at most that many (one compiled size)
    chunks = -(-size // BATCH_CHUNK)
    chunk = -(-size // chunks)
    rows = np.arange(chunks * chunk) % n  # a few more than asked where chunks do not divide it evenly
    big = [(needle[r], start[r], goal[r], r) for r in rows.reshape(chunks, chunk)]
    batch_s = float("nan")
    if batch_repeats:
        if chunk != n:
            run(*big[0])  # compiles the batched program (the test-set pass above compiled its own size)
        t0 = time.perf_counter()
        for _ in range(batch_repeats):
            for part in big:
                run(*part)
        batch_s = (time.perf_counter() - t0) / batch_repeats
    times = []
    if timed_queries != 0:
        run(needle[0], start[0], goal[0], 0)  # compiles the one-query program
        for i in range(min(n, timed_queries or n)):
            t0 = time.perf_counter()
            run(needle[i], start[i], goal[i], i)
            times.append(time.perf_counter() - t0)
    ok = plan.success
    return {
        "problems": n,
        "success_rate": float(ok.mean()),
        "collision_rate": float((plan.collision | ~plan.start_valid).mean()),
        "time_out_rate": float(plan.time_out.mean()),
        "invalid_starts": int((~plan.start_valid).sum()),
        "far_starts": int(far_starts(needle, start).sum()),
        "path_length_mm": float(plan.path_length_mm[ok].mean()) if ok.any() else None,
        "steps_mean": float(plan.steps[ok].mean()) if ok.any() else None,
        "planning_time_ms_mean": 1e3 * float(np.mean(times)) if times else None,
        "planning_time_ms_median": 1e3 * float(np.median(times)) if times else None,
        "timed_queries": len(times),
        "single_query_engine": auto_engine(1),  # what Policy.plan ran the timed queries with
        "batch_plans_per_s": len(rows) / batch_s,
        "batch_size": len(rows),
        "batch_chunk": chunk,
        "ensemble": policy.members,
        "shield": shield,
        "device": str(jax.devices()[0].device_kind),
        "backend": jax.default_backend(),
    }
