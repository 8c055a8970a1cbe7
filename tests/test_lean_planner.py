"""The lean one-query CPU path (numba) against the JAX planning program: the same verdict on every
problem, the same actions up to float32 rounding, the same trajectories; and Policy.plan's choice
of engine. The full agreement on paper300, held-out 3000 and general1000 is
``python experiments/bench_plan.py --agreement`` (experiments/results/bench_plan)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from regrasp_mjx.policy import load_policy
from regrasp_mjx.sampling import episode_needles, episode_poses, load_testset
from regrasp_mjx.testset import make_testset

# The JAX path computes in float32 and this one its geometry in float64 (the network in float32 in
# both): the observations round differently, the network amplifies it and a plan carries it along.
# Seen (experiments/results/bench_plan/agreement.md): up to 2.1e-5 in an action of a plan that ends
# before the horizon, 1.8e-4 by the last step of a 100-step time-out.
ACTION_ATOL = 1e-4
ACTION_ATOL_TIME_OUT = 1e-3


def _agree(policy, episodes, shield=True):
    """Each problem planned one at a time by the lean path and all at once by the JAX path."""
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes) if policy.general else {}
    batch = policy.plan(needle, start, goal, check_grasp=False, shield=shield, engine="jax", **needles)
    worst = 0.0
    for i in range(len(needle)):
        one = policy.plan(
            needle[i], start[i], goal[i], check_grasp=False, shield=shield, engine="lean",
            **{k: v[i] for k, v in needles.items()},
        )  # fmt: skip
        for field in ("start_valid", "success", "collision", "time_out", "steps"):
            assert getattr(one, field) == getattr(batch, field)[i], (i, field)
        n = int(one.steps)  # one query's trajectory is its own; the batch's runs to its longest plan
        assert one.poses.shape == (n + 1, 7) and one.actions.shape == (n, 6)
        diff = float(np.abs(one.actions - batch.actions[i, :n]).max()) if n else 0.0
        assert diff <= ACTION_ATOL_TIME_OUT, i
        if not one.time_out:
            worst = max(worst, diff)
        np.testing.assert_allclose(one.poses, batch.poses[i, : n + 1], atol=1e-4 if one.time_out else 1e-5)
        assert one.path_length_mm == pytest.approx(batch.path_length_mm[i], abs=1e-4)
    assert worst <= ACTION_ATOL
    return batch


def test_the_lean_path_gives_the_jax_paths_verdicts_on_paper300_shielded_and_bare():
    policy = load_policy("default")
    episodes = load_testset("paper300")[0]
    shielded = _agree(policy, episodes)
    assert shielded.success.mean() == pytest.approx(1.0)  # the shipped default (README)
    bare = _agree(policy, episodes, shield=False)
    assert bare.collision.sum() >= 1  # the bare network collides on a few: the shield is exercised above


def test_the_lean_path_on_held_out_problems_an_ensemble_and_a_general_policy():
    default = load_policy("default")
    _agree(default, make_testset(100, 2022, default.env_config))
    _agree(load_policy("ensemble3"), jax_rows(load_testset("paper300")[0], 60))
    _agree(load_policy("general"), jax_rows(load_testset("general1000")[0], 100))


def jax_rows(episodes, n):
    return jax.tree.map(lambda x: x[:n], episodes)


def test_policy_plan_takes_the_lean_path_for_one_query_on_the_cpu():
    policy = load_policy("exact")
    needle, start, goal = (x[0] for x in episode_poses(load_testset("paper300")[0]))
    auto = policy.plan(needle, start, goal)
    assert ("lean", True) in policy._planners and (False, True) not in policy._planners
    ref = policy.plan(needle, start, goal, engine="jax")
    assert auto.success == ref.success and auto.steps == ref.steps
    assert auto.poses.shape == ref.poses.shape == (ref.steps + 1, 7)
    batch = policy.plan(needle[None], start[None], goal[None])  # a batch of one: still lean, batch axis kept
    assert batch.success.shape == (1,) and batch.steps[0] == ref.steps
    with pytest.raises(ValueError, match="engine='fast' is not accepted; accepted: 'auto', 'jax', 'lean'"):
        policy.plan(needle, start, goal, engine="fast")
    with pytest.raises(ValueError, match="engine='lean' plans one query at a time; got 2"):
        policy.plan(np.stack([needle] * 2), np.stack([start] * 2), np.stack([goal] * 2), engine="lean")


def test_the_default_goal_on_the_lean_path_is_the_jax_one():
    """Policy.plan without a goal computes it from the goal grasp: in numba on the lean path."""
    policy = load_policy("general")
    lean = policy._lean_planner(True)
    rng = np.random.default_rng(3)
    needle, _, _ = episode_poses(load_testset("general1000")[0])
    lo, hi = (np.array(x) for x in zip(*[policy.trained_ranges()[k] for k in policy._TASK_INPUTS[:4]]))
    grasp = rng.uniform(lo, hi, (50, 4)) * np.array([1, 1e-3, 1, 1])
    radii = rng.uniform(0.004, 0.012, 50)
    ref = policy._default_goal(needle[:50], grasp, np.stack([radii, radii], 1))
    for i in range(50):
        np.testing.assert_allclose(lean.goal(needle[i], grasp[i], radii[i]), ref[i], atol=2e-6)
