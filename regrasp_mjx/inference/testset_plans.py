"""A policy's plans of test-set problems: each row planned through ``Policy.plan`` on its own
needle, the outcomes bare and shielded, and the two engines of ``Policy.plan`` (lean CPU, JAX)
compared problem by problem (``python -m regrasp_mjx.evaluate --agreement``)."""

from __future__ import annotations

import numpy as np

from regrasp_mjx.envs.rollout import summarize
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
    (``(row, field)`` where a verdict or a trajectory's length differs), and per problem ``[N]`` the
    largest difference in an action (``action_diff``) and a pose (``pose_diff``), the path lengths'
    difference (``path_diff_mm``), ``steps`` and ``time_out``."""
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes)  # each problem on its own needle, as plan_testset plans them
    batch = policy.plan(needle, start, goal, check_grasp=False, shield=shield, engine="jax", **needles)
    out = {
        "batch": batch,
        "differ": [],
        **{k: np.zeros(len(needle)) for k in ("action_diff", "pose_diff", "path_diff_mm")},
    }
    for i in range(len(needle)):
        kw = {k: v[i] for k, v in needles.items()}
        one = policy.plan(needle[i], start[i], goal[i], check_grasp=False, shield=shield, engine="lean", **kw)
        out["differ"] += [(i, f) for f in VERDICTS if getattr(one, f) != getattr(batch, f)[i]]
        n = int(one.steps)  # one query's trajectory is its own; the batch's runs on to its longest plan
        if (i, "steps") in out["differ"] or one.poses.shape != (n + 1, 7) or one.actions.shape != (n, 6):
            out["differ"] += [(i, "trajectory")]
            continue
        out["action_diff"][i] = float(np.abs(one.actions - batch.actions[i, :n]).max()) if n else 0.0
        out["pose_diff"][i] = float(np.abs(one.poses - batch.poses[i, : n + 1]).max())
        out["path_diff_mm"][i] = abs(float(one.path_length_mm) - float(batch.path_length_mm[i]))
    return {**out, "steps": np.asarray(batch.steps), "time_out": np.asarray(batch.time_out, bool)}
