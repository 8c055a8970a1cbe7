"""Jaws that open on the way on the lean CPU path (issue 67): the lean planner opens them where the
environment does (the sweep's check points and slack, worked by hand at its bound), plans with them
open as the JAX program does (the same verdicts, the same step they opened before, poses to float
rounding), and ``closed_loop_step`` carries the opening in and out, equal to the jitted step and to
the jitted closed loop."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.lean_collision import fixed_ends
from regrasp_mjx.envs.lean_jaw import sweep_keeps
from regrasp_mjx.inference.plans import auto_engine
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.testset_plans import engine_agreement
from regrasp_mjx.world.sampling import Episode, episode_poses
from regrasp_mjx.world.testsets import make_testset
from tests.test_jaw import JAW_LENGTH, _wire_past_the_tip

OPEN40 = "experiments/results/jaw_on_the_way/policy_open40"  # a 3x512 teacher trained to open to 40 degrees
# the lean path's geometry is float64, the JAX path's float32 (tests/test_lean_planner.py's bounds;
# seen here: 5.5e-7 in a pose, 2.1e-5 in an action on paper300 and held-out problems)
POSE_ATOL, ACTION_ATOL = 5e-5, 2e-4


@pytest.fixture(scope="module")
def open40():
    return load_policy(OPEN40)


def _agree(policy, episodes, shield):
    """Every problem planned by both engines: the same verdicts and opening steps, poses and actions
    within float rounding (none of these plans times out)."""
    r = engine_agreement(policy, episodes, shield)
    assert r["differ"] == [] and not r["time_out"].any()
    assert r["pose_diff"].max() <= POSE_ATOL and r["action_diff"].max() <= ACTION_ATOL
    return r


def test_the_lean_sweep_opens_exactly_where_its_room_keeps_the_margin(open40):
    """The wire 0.5 mm (the margin) plus the slack past jaw a's tip at 30 degrees, a check point of the
    sweep from 20 to 40 (10 intervals of 2 degrees: 20, 22, ..., 40), the jaw passing it by on either
    side: the room is the gap less the slack, so 2 um more gap opens the jaws and 2 um less keeps them
    at 20 degrees, on the lean path and in the environment alike; and the planner's step reports it."""
    planner = open40.lean(True)
    jaws, geo = planner.jaws, planner.geo
    margin = open40.env_config.jaw_open_margin_mm * 1e-3
    assert margin == 5e-4 and jaws.margin == pytest.approx(margin, rel=1e-7)
    # a jaw point 9.6 mm from the hinge moves 9.6 mm x rad(2 deg) / 2 between check points (the jaws turn
    # by half the opening): the slack is a quarter of the check points' spacing in opening, 0.0838 mm
    slack = JAW_LENGTH * math.radians(2.0) / 4.0
    assert jaws.slack == pytest.approx(slack, rel=1e-6) and slack == pytest.approx(8.3776e-5, rel=1e-4)
    # from the middle check point (30 degrees) the jaws turn at most 5 degrees: 9.6 mm x rad(5) = 0.838 mm
    assert jaws.turn == pytest.approx(JAW_LENGTH * math.radians(5.0), rel=1e-6)
    np.testing.assert_allclose(
        np.degrees(np.arctan2(jaws.sweep[:, 0, 0, 1], jaws.sweep[:, 0, 0, 2])) * 2, 20 + 2 * np.arange(11)
    )
    env = RegraspEnv(open40.env_config)
    scratch = np.empty((len(jaws.sweep), 2, 3))
    radii = (float(np.float32(5.4e-3)), float(np.float32(0.25e-3)))
    for gap, opens in ((margin + slack + 2e-6, True), (margin + slack - 2e-6, False), (3e-4, False)):
        needle, ee = _wire_past_the_tip(env.scene, 30.0, gap)
        n = needle / np.r_[1, 1, 1, [np.linalg.norm(needle[3:])] * 4]
        fixed = fixed_ends(geo, False, tuple(n[:3]), tuple(n[3:]), *radii)
        assert sweep_keeps(jaws, geo, fixed, tuple(ee[:3]), tuple(ee[3:]), scratch) == opens, gap
        episode = Episode.from_poses(*(jnp.asarray(x[None], jnp.float32) for x in (needle, ee, ee)))
        es = jax.vmap(env.reset_from)(episode).pipeline_state
        room = float(jax.vmap(env.opening_room, in_axes=(0, None))(es, 40.0)[0])
        assert room == pytest.approx(gap - slack, abs=1e-6) and (room >= env.jaw_margin) == opens, gap
        # the lean closed-loop step and the JAX one open the jaws before the step, or not, alike
        _, _, _, lean_jaw = open40.closed_loop_step(needle, ee, jaw_deg=20.0)  # toward the goal grasp
        _, _, _, jax_jaw = open40.closed_loop_step(needle[None], ee[None], jaw_deg=20.0)
        assert lean_jaw == jax_jaw[0] == (40.0 if opens else 20.0), gap


def test_the_lean_sweeps_verdict_is_the_environments_near_the_needle(open40, paper_testset):
    """1200 poses about paper300's starts (1.5 mm and 10 degrees of scatter): the lean sweep's verdict
    (bounds that skip pairs and check points) is the environment's room against its margin wherever
    the room is more than 1e-6 m from it (float32 there, float64 here), and both verdicts occur."""
    planner = open40.lean(True)
    env = RegraspEnv(open40.env_config)
    rng = np.random.default_rng(5)
    needle, start, _ = (np.repeat(x[:300], 4, axis=0) for x in episode_poses(paper_testset[0]))
    turn = rng.normal(0.0, math.radians(10.0) / 2.0, (len(start), 3))  # small rotations as quaternions
    ee = start.copy()
    ee[:, :3] += rng.normal(0.0, 1.5e-3, (len(start), 3))
    ee[:, 3:] = np.stack([_qmul(np.r_[1.0, t], q) for t, q in zip(turn, start[:, 3:])])
    ee[:, 3:] /= np.linalg.norm(ee[:, 3:], axis=1, keepdims=True)
    episode = Episode.from_poses(*(jnp.asarray(x, jnp.float32) for x in (needle, ee, ee)))
    es = jax.jit(jax.vmap(env.reset_from))(episode).pipeline_state
    room = np.asarray(jax.jit(jax.vmap(env.opening_room, in_axes=(0, None)))(es, 40.0))
    scratch = np.empty((len(planner.jaws.sweep), 2, 3))
    lean = np.zeros(len(ee), bool)
    for i in range(len(ee)):
        n, e = (np.float64(np.float32(x)) for x in (needle[i], ee[i]))
        n[3:], e[3:] = n[3:] / np.linalg.norm(n[3:]), e[3:] / np.linalg.norm(e[3:])
        fixed = fixed_ends(planner.geo, False, tuple(n[:3]), tuple(n[3:]), 5.4e-3, 0.25e-3)
        lean[i] = sweep_keeps(planner.jaws, planner.geo, fixed, tuple(e[:3]), tuple(e[3:]), scratch)
    decided = np.abs(room - env.jaw_margin) > 1e-6
    np.testing.assert_array_equal(lean[decided], room[decided] >= env.jaw_margin)
    assert 0.2 < lean.mean() < 0.8 and decided.mean() > 0.99


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def test_the_lean_path_carries_the_jaws_as_the_jax_program_on_paper300_rows(open40, paper_testset):
    """The first 48 problems (the jaws open before step 0, 1, 2 or 3 and, on row 43, never), bare
    and shielded; Policy.plan's automatic engine is the lean one for such a policy too."""
    episodes = jax.tree.map(lambda x: x[:48], paper_testset[0])
    for shield in (True, False):
        r = _agree(open40, episodes, shield)
        assert set(r["opened_at"]) == {-1, 0, 1, 2, 3} and r["opened_at"][43] == -1
    assert auto_engine(1, open40) == "lean"
    needle, start, goal = (x[0] for x in episode_poses(paper_testset[0]))
    plan = open40.plan(needle, start, goal)
    assert ("lean", True) in open40._programs and bool(plan.success)


@pytest.mark.slow  # 900 problems, each engine bare and shielded
def test_the_lean_path_carries_the_jaws_on_all_of_paper300_and_held_out_problems(open40, paper_testset):
    """Every paper300 problem and 300 held-out ones (seed 2022) with the teacher, and paper300 with the
    network of student_v3 (the default until 2026-11-29) opening to 40 degrees (a policy not trained to: one bare plan collides,
    so the shield's alternatives run with the jaws open)."""
    held_out = make_testset(300, 2022, open40.env_config)
    for episodes in (paper_testset[0], held_out):
        for shield in (True, False):
            _agree(open40, episodes, shield)
    untrained = load_policy("student_v3").with_env(jaw_open_deg=40.0)
    bare = _agree(untrained, paper_testset[0], False)
    assert bare["batch"].collision.sum() >= 1
    shielded = _agree(untrained, paper_testset[0], True)
    assert shielded["batch"].collision.sum() < bare["batch"].collision.sum()


def _lean_loop(policy, needle, start, goal, check=None):
    """One problem driven by the lean closed-loop step on exact estimates, carrying the jaws' opening
    from the scene's: the poses, the step the jaws opened before (-1 never) and the steps taken;
    ``check(t, ee, jaw_deg, lean_outputs)`` at each step."""
    ee, jaw_deg, opened_at, poses = start, 20.0, -1, [start]
    for t in range(policy.env_config.horizon):
        out = policy.closed_loop_step(needle, ee, goal, t=t, jaw_deg=jaw_deg, stop_tolerance=1.0)
        if check is not None:
            check(t, ee, jaw_deg, out)
        action, nxt, at_goal, after = out
        if at_goal:
            return np.array(poses), opened_at, t
        opened_at = t if after > jaw_deg else opened_at
        ee, jaw_deg = nxt, after
        poses.append(nxt)
    return np.array(poses), opened_at, policy.env_config.horizon


def test_the_lean_closed_loop_step_carries_the_jaws_as_the_jax_step(open40, paper_testset):
    """Six problems stepped to their goals on the lean step, each state stepped again by the JAX
    program (a batch of one): the same stop verdicts, openings, next poses and actions."""
    needle, start, goal = (x[:6] for x in episode_poses(paper_testset[0]))
    openings = []

    def same(t, ee, jaw_deg, lean):
        ref = open40.closed_loop_step(
            needle[i][None], ee[None], goal[i][None], t=t, jaw_deg=[jaw_deg], stop_tolerance=1.0
        )
        assert lean[2] == ref[2][0] and lean[3] == ref[3][0], (i, t)
        np.testing.assert_allclose(lean[0], ref[0][0], atol=1e-4, err_msg=f"row {i} step {t}")
        np.testing.assert_allclose(lean[1], ref[1][0], atol=1e-6, err_msg=f"row {i} step {t}")

    for i in range(len(needle)):
        openings.append(_lean_loop(open40, needle[i], start[i], goal[i], same)[1])
    assert set(openings) >= {0, 1, 2}


@pytest.mark.slow  # the executor compiled on the CPU
def test_the_lean_closed_loop_is_the_jitted_closed_loop(open40, paper_testset):
    """Exact views, one frame, the task's own stop tolerance: the jitted closed loop (Policy.execute)
    and the lean step driven by hand go through the same poses, open the jaws before the same step and
    end at the same step."""
    needle, start, goal = (x[:12] for x in episode_poses(paper_testset[0]))
    r = open40.execute(needle, start, goal, frames="one", stop_tolerance=1.0, jaw_sigmas=0.0)
    assert r["success"].all() and (r["opened_at"] >= 0).all() and len(set(r["opened_at"])) >= 3
    for i in range(len(needle)):
        poses, opened_at, steps = _lean_loop(open40, needle[i], start[i], goal[i])
        assert (opened_at, steps) == (r["opened_at"][i], r["steps"][i]), i
        np.testing.assert_allclose(poses, r["poses"][i, : steps + 1], atol=POSE_ATOL, err_msg=f"row {i}")


def test_closed_loop_step_takes_the_jaws_opening_as_state(open40, paper_testset):
    """A policy that opens its jaws needs their opening in (one of its two) and gives it out; a policy
    whose jaws stay is called as before and refuses another opening."""
    needle, start, goal = (x[0] for x in episode_poses(paper_testset[0]))
    with pytest.raises(ConfigError, match="jaw_deg is required for a policy whose jaws open on the way"):
        open40.closed_loop_step(needle, start, goal)
    for bad in (30.0, "40", [20.0, 40.0], float("nan")):
        with pytest.raises(ConfigError, match=r"jaw_deg=.* is not accepted: the jaws' opening now, 20.0 .* or 40.0"):
            open40.closed_loop_step(needle, start, goal, jaw_deg=bad)
    # opened already: the step moves with them open and says so; a batch takes one opening per row
    action, nxt, at_goal, jaw_deg = open40.closed_loop_step(needle, start, goal, jaw_deg=40.0)
    assert jaw_deg == 40.0 and not at_goal and nxt.shape == (7,) and action.shape == (6,)
    batch = open40.closed_loop_step(
        np.stack([needle] * 2), np.stack([start] * 2), np.stack([goal] * 2), jaw_deg=[20.0, 40.0]
    )
    assert len(batch) == 4 and batch[3].shape == (2,) and batch[3][1] == 40.0
    default = load_policy("student_v3")  # a policy whose jaws stay (the default until 2026-11-29)
    assert len(default.closed_loop_step(needle, start, goal)) == 3
    assert len(default.closed_loop_step(needle, start, goal, jaw_deg=20.0)) == 3
    with pytest.raises(ConfigError, match=r"jaw_deg=40.0 is not accepted: this policy's jaws stay at its scene's 20.0"):
        default.closed_loop_step(needle, start, goal, jaw_deg=40.0)
