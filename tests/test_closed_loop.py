"""Closed-loop regrasping: zero noise reproduces `plan`, the noise model's statistics, and the stop
decided by the estimate alone."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx import load_policy
from regrasp_mjx.envs.estimates import NeedleNoise, episode_bias, frame_estimate
from regrasp_mjx.world.sampling import episode_poses


@pytest.fixture(scope="module")
def policy():
    # a policy whose jaws stay (the default until 2026-11-29): its step takes no opening and returns three
    # values; the default's, whose jaws open on the way, in tests/test_lean_jaw.py and tests/test_camera_loop.py
    return load_policy("student_v3")


def _angle(q1, q2):
    return 2 * np.arccos(np.clip(np.abs(np.sum(np.asarray(q1) * np.asarray(q2), -1)), 0, 1))


@pytest.mark.slow  # 89 s on the 2-core VM (the quick tier's 20 minutes; CI runs the long tier too)
def test_zero_noise_closed_loop_equals_plan(policy, paper_testset):
    episodes, _ = paper_testset
    needle, start, goal = (x[:24] for x in episode_poses(episodes))
    plan = policy.plan(needle, start, goal, check_grasp=False)
    run = policy.execute(needle, start, goal, frames="one", warmup_frames=1, stop_tolerance=1.0)
    np.testing.assert_array_equal(run["success"], plan.success)
    np.testing.assert_array_equal(run["steps"], plan.steps)
    longest = plan.poses.shape[1]  # a plan's trajectories end with its longest plan, the loop's at the horizon
    np.testing.assert_allclose(run["poses"][:, :longest], plan.poses, atol=1e-5)
    np.testing.assert_allclose(
        run["poses"][:, longest:], np.repeat(plan.poses[:, -1:], run["poses"].shape[1] - longest, 1), atol=1e-5
    )
    assert (run["stopped"] == run["success"]).all()  # estimate = truth: every stop is a success


def test_noise_model_statistics():
    needle = jnp.tile(jnp.array([[0.001, -0.002, 0.003, 0.5, 0.5, 0.5, 0.5]]), (20000, 1))
    est = np.asarray(frame_estimate(jax.random.PRNGKey(0), needle, 0.5))
    d = est[:, :3] - np.asarray(needle[:, :3])
    np.testing.assert_allclose(d.mean(0), 0.0, atol=2e-5)  # zero mean (std of the mean 3.5 um)
    np.testing.assert_allclose(d.std(0), 0.5e-3, rtol=0.03)  # sigma per axis
    angle = _angle(est[:, 3:], needle[:, 3:])
    assert abs(math.degrees(np.sqrt(np.mean(angle**2))) - 2.5) < 0.08  # 5 sigma degrees, RMS
    assert np.allclose(np.linalg.norm(est[:, 3:], axis=1), 1.0, atol=1e-6)
    biased = np.asarray(episode_bias(jax.random.PRNGKey(1), needle, 0.25))
    np.testing.assert_allclose(np.linalg.norm(biased[:, :3] - np.asarray(needle[:, :3]), axis=1), 0.25e-3, rtol=1e-4)
    np.testing.assert_allclose(np.degrees(_angle(biased[:, 3:], needle[:, 3:])), 1.25, atol=2e-3)
    assert np.asarray(frame_estimate(jax.random.PRNGKey(0), needle, 0.0) == needle).all()
    with pytest.raises(ValueError, match="sigma_mm"):
        NeedleNoise(sigma_mm=-1.0)


def test_stopping_uses_only_the_estimate(policy, paper_testset):
    episodes, _ = paper_testset
    needle, _, goal = (x[0] for x in episode_poses(episodes))
    # At the goal grasp on the estimate: stop, whatever the true needle is.
    action, nxt, at_goal = policy.closed_loop_step(needle, goal)
    assert at_goal and not action.any()
    np.testing.assert_allclose(nxt, goal, atol=1e-6)  # float32 round trip
    # At the true goal but the estimate 2 mm off: the step does not know the truth, so it moves on.
    off = needle.copy()
    off[2] += 2e-3
    action, nxt, at_goal = policy.closed_loop_step(off, goal)
    assert not at_goal and np.abs(action).max() > 0 and not np.array_equal(nxt, goal)
    # In simulation, a stop on a biased estimate is judged on the true needle.
    needle, start, goal = (x[:16] for x in episode_poses(episodes))
    run = policy.execute(needle, start, goal, NeedleNoise(0.0, 1.5), frames="each", warmup_frames=1, stop_tolerance=1.0)
    assert (run["success"] <= run["stopped"]).all() and (run["stopped"] & ~run["success"]).any()


def test_one_query_through_the_jax_program_comes_back_as_one(policy, paper_testset):
    """A query the lean path does not take (``clearance_mm``; every query on a GPU host) returns one
    action and one pose, as the lean path does: CameraLoop unpacks ``next_ee`` as a 7-vector (a
    [1, 7] array failed it on an H200, 2026-11-29)."""
    episodes, _ = paper_testset
    needle, start, goal = (x[0] for x in episode_poses(episodes))
    a, nxt, done = policy.closed_loop_step(needle, start, goal, clearance_mm=0.05)
    assert a.shape == (6,) and nxt.shape == (7,) and np.ndim(done) == 0 and not done
    a1, nxt1, _ = policy.closed_loop_step(needle, start, goal)  # the lean path: the same step
    np.testing.assert_allclose(nxt1, nxt, atol=1e-3)


@pytest.mark.slow
def test_one_closed_loop_step_on_the_lean_path_is_the_jax_program(policy, paper_testset):
    """One query on the CPU takes the lean numba step; a batch takes the JAX program: the same
    stop verdicts, actions to float32 rounding and the same next poses, at the start, along the
    plans, at their goals and at the horizon's last step (its shield's own perturbations), with the
    default goal and a given one."""
    episodes, _ = paper_testset
    needle, start, goal = (x[:40] for x in episode_poses(episodes))
    plan = policy.plan(needle, start, goal, check_grasp=False)
    rows = np.arange(len(needle))
    cases = [(start, 0, goal), (plan.poses[:, 2], 2, goal), (plan.poses[rows, plan.steps], 5, goal)]
    cases += [(plan.poses[:, 1], 99, None)]
    stops = 0
    for ee, t, given in cases:
        a, nxt, done = policy.closed_loop_step(needle, ee, given, t=t)
        for i in rows:
            a1, nxt1, done1 = policy.closed_loop_step(needle[i], ee[i], None if given is None else given[i], t=t)
            assert done1 == done[i], (t, i)
            np.testing.assert_allclose(a1, a[i], atol=1e-4, err_msg=f"t {t} row {i}")
            np.testing.assert_allclose(nxt1, nxt[i], atol=1e-6, err_msg=f"t {t} row {i}")
        stops += int(done.sum())
    assert stops > 20  # the goal poses stop (most: the loop's own tolerance is the policy's, 0.8)
