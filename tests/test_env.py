"""RegraspEnv: collisions, a scripted regrasp, tunnelling, the start distribution, jit/vmap, errors."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from brax.envs.wrappers.training import AutoResetWrapper, VmapWrapper

from regrasp_mjx.core import geometry as g
from regrasp_mjx.core.config import ConfigError, EnvConfig, SceneConfig, TaskConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.host import HostEnv
from regrasp_mjx.world.sampling import Episode


def _rows(testset, idx) -> Episode:
    episodes, _ = testset
    return jax.tree.map(lambda x: jnp.asarray(x[np.asarray(idx)], jnp.float32), episodes)


def _toward_goal(env: RegraspEnv):
    """A straight-line scripted controller: translate and rotate toward the goal, clipped."""

    def act(es):
        dp = (es.goal_pos - es.ee_pos) / env.max_dp
        dq = g.quat_mul(es.goal_quat, jaxlie.SO3(es.ee_quat).inverse().wxyz)
        return jnp.clip(jnp.concatenate([dp, jaxlie.SO3(dq).log() / env.max_drot]), -1.0, 1.0)

    return jax.jit(jax.vmap(act))


# ---- collisions ------------------------------------------------------------------------------
def test_goal_with_open_jaws_is_free_and_jaw_through_the_wire_collides(env, distance_fn, paper_testset):
    ep = _rows(paper_testset, range(300))
    at_goal = distance_fn(ep.needle_pos, ep.needle_quat, ep.goal_pos, ep.goal_quat)
    assert np.all(np.asarray(at_goal).min(axis=1) > 0.0)
    # Shift the tool along its y axis by d* tan(10 deg): the axis of jaw a then meets the wire.
    y_axis = np.asarray(g.rotation_matrix(ep.goal_quat))[:, :, 1]
    shift = -np.asarray(ep.goal_depth)[:, None] * math.tan(math.radians(10.0)) * y_axis
    through = distance_fn(ep.needle_pos, ep.needle_quat, ep.goal_pos + shift, ep.goal_quat)
    through = np.asarray(through)
    assert np.all(through.min(axis=1) < -0.5e-3)  # sunk by at least the wire's and jaw's radii
    needle_pairs = [
        k for k, (_, j) in enumerate(env.scene.pairs) if j in {c.geom_id for c in env.scene.needle_capsules}
    ]
    assert np.all(through[:, needle_pairs].min(axis=1) < 0.0)


def test_regrasping_tool_against_the_grasping_tool_collides(env, distance_fn, paper_testset):
    ep = _rows(paper_testset, range(4))
    # The regrasping tool placed on the grasping tool (world origin, same orientation).
    pos = jnp.zeros((4, 3))
    quat = jnp.tile(jnp.array([1.0, 0, 0, 0]), (4, 1))
    dist = np.asarray(distance_fn(ep.needle_pos, ep.needle_quat, pos, quat))
    grasp_ids = {c.geom_id for c in env.scene.grasp_capsules}
    grasp_pairs = [k for k, (_, j) in enumerate(env.scene.pairs) if j in grasp_ids]
    assert np.all(dist[:, grasp_pairs].min(axis=1) < 0.0)


# ---- a scripted regrasp, and what a step may not do ----------------------------------------------
def test_scripted_approach_succeeds_with_plus_one_on_its_last_step(env, jit_env, paper_testset):
    _, reset_from, step = jit_env
    act = _toward_goal(env)
    state = reset_from(_rows(paper_testset, range(300)))
    rewards, dones, successes = [], [], []
    for _ in range(15):
        state = step(state, act(state.pipeline_state))
        rewards.append(np.asarray(state.reward))
        dones.append(np.asarray(state.done))
        successes.append(np.asarray(state.metrics["success"]))
    rewards, dones, successes = map(np.stack, (rewards, dones, successes))
    first_done = np.argmax(dones > 0, axis=0)
    ended = dones.max(axis=0) > 0
    won = ended & (successes[first_done, np.arange(300)] > 0)
    assert won.sum() >= 10, f"the straight line should reach some goals, got {won.sum()}"
    for i in np.flatnonzero(won)[:10]:
        t = first_done[i]
        assert rewards[t, i] == pytest.approx(1.0)
        np.testing.assert_allclose(rewards[:t, i], -0.02, atol=1e-7)
        assert np.all(dones[:t, i] == 0)
    lost = ended & ~won
    assert np.all(rewards[first_done[lost], np.flatnonzero(lost)] == pytest.approx(-1.0))


def test_rollout_ends_each_episode_as_a_hand_stepped_loop_does(env, jit_env, paper_testset):
    from regrasp_mjx.envs.rollout import rollout

    _, reset_from, step = jit_env
    act = _toward_goal(env)
    rows, k = _rows(paper_testset, range(64)), 6  # k steps: some episodes end within them, some do not
    start = reset_from(rows)
    # the rows' own starts, and the same problems started on the grasping tool (a colliding start)
    bad = start.pipeline_state.replace(ee_pos=jnp.zeros((64, 3)))
    starts = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), start, reset_from(rows.replace(start_pos=bad.ee_pos)))
    roll = jax.jit(
        lambda s: rollout(
            env, lambda st, t: act(st.pipeline_state), s, max_steps=k, gamma=0.9, trace=lambda s, a, n: n.reward
        )
    )
    out = jax.tree.map(np.asarray, roll(starts))

    state, rewards, dones, metrics = start, [], [], []
    for _ in range(k):  # by hand: every row stepped k times, ends read off afterwards
        state = step(state, act(state.pipeline_state))
        rewards.append(np.asarray(state.reward))
        dones.append(np.asarray(state.done) > 0)
        metrics.append({k: np.asarray(state.metrics[k]) > 0 for k in ("success", "collision", "time_out")})
    rewards, dones = np.stack(rewards), np.stack(dones)
    ended = dones.any(axis=0)
    first = np.where(ended, np.argmax(dones, axis=0), k - 1)
    cols = np.arange(64)
    assert ended.sum() >= 5 and (~ended).sum() >= 1, "the check needs episodes that end and one that does not"
    for name in ("success", "collision", "time_out"):
        expect = ended & np.stack([m[name] for m in metrics])[first, cols]
        np.testing.assert_array_equal(out.__getattribute__(name)[:64], expect, err_msg=name)
    np.testing.assert_array_equal(out.steps[:64], first + 1)  # k (the limit) where none ended
    upto = np.arange(k)[:, None] <= first[None, :]
    np.testing.assert_allclose(
        out.discounted_return[:64], (0.9 ** np.arange(k)[:, None] * rewards * upto).sum(0), rtol=1e-5
    )
    np.testing.assert_array_equal(out.trace[:, :64], np.where(upto, rewards, 0.0))  # zeros after the end
    # a colliding start: ended before any step, as a collision
    assert not out.start_valid[64:].any() and out.collision[64:].all() and not out.success[64:].any()
    assert (out.steps[64:] == 0).all() and (out.trace[:, 64:] == 0).all() and (out.discounted_return[64:] == 0).all()


def test_a_compacted_rollout_ends_every_episode_as_the_whole_batch_does(env, jit_env, paper_testset):
    """``rollout(compact=True)`` carries on with the few live rows alone: same outcomes and traces."""
    from regrasp_mjx.envs.rollout import COMPACT, rollout

    _, reset_from, _ = jit_env
    toward = _toward_goal(env)
    start = reset_from(_rows(paper_testset, range(64)))
    slow = jnp.arange(64) % 21 == 5  # 3 rows crawl (per-row data in the state's info) and time out
    start = start.replace(info={**start.info, "slow": slow})
    widths = []  # the batch sizes act was traced with

    def act(st, t):
        widths.append(st.obs.shape[0])
        return jnp.where(st.info["slow"][:, None], 0.01, 1.0) * toward(st.pipeline_state)

    trace = lambda s, a, n: (n.pipeline_state.ee_pos, a)  # noqa: E731
    whole, narrow = (
        jax.tree.map(
            np.asarray, jax.jit(lambda s, c=c: rollout(env, act, s, max_steps=40, trace=trace, compact=c))(start)
        )
        for c in (False, True)
    )
    assert widths == [64, 64, 64 // COMPACT]  # the compacted program narrowed once
    assert whole.time_out.sum() == 0 and (whole.steps[np.asarray(slow)] == 40).all()  # ran to the limit
    assert (whole.steps[~np.asarray(slow)] < 20).all()  # the others ended early
    for name in ("start_valid", "success", "collision", "time_out", "steps", "path_length_mm", "discounted_return"):
        np.testing.assert_array_equal(getattr(narrow, name), getattr(whole, name), err_msg=name)
    for a, b in zip(narrow.trace, whole.trace):
        np.testing.assert_array_equal(a, b)


def test_an_ended_row_is_stepped_by_no_motion_and_the_outcomes_stay(env, jit_env, paper_testset, monkeypatch):
    """A row that has ended is held; ``rollout`` steps it by a zero action (which the continuous
    collision test proves at once) instead of its policy's, and every outcome is as before."""
    from regrasp_mjx.envs import rollout as r

    _, reset_from, _ = jit_env
    toward = _toward_goal(env)
    start = reset_from(_rows(paper_testset, range(16)))
    act = lambda st, t: toward(st.pipeline_state)  # noqa: E731 - straight at the goal: some rows hit the wire
    given = []

    def step(state, a):
        jax.debug.callback(lambda a: given.append(np.asarray(a)), a, ordered=True)
        return jax.vmap(env.step)(state, a)

    runs = {}
    for hold in (True, False):
        monkeypatch.setattr(r, "HOLD_STILL", hold)
        given.clear()
        out = jax.tree.map(np.asarray, jax.jit(lambda s: r.rollout(env, act, s, max_steps=12, step=step))(start))
        runs[hold] = (out, np.stack(given))
    (out, moved), (before, _) = runs[True], runs[False]
    assert out.collision.any() and out.success.any()  # rows ended both ways, at different steps
    live = np.arange(len(moved))[:, None] < out.steps[None, :]  # [step, row]: the row was live at that step
    assert len(moved) == out.steps.max() and (~live).sum() > len(moved)
    assert (moved[~live] == 0).all() and (np.abs(moved[live]).sum(-1) > 0).all()
    for name in ("start_valid", "success", "collision", "time_out", "steps", "path_length_mm", "discounted_return"):
        np.testing.assert_array_equal(getattr(out, name), getattr(before, name), err_msg=name)


def test_a_stopping_rule_ends_episodes_in_place_of_the_environment(env, jit_env, paper_testset):
    """``rollout(stop=...)``: the rule ends rows before a step (its success or not, ``stopped``),
    reaching the true goal no longer ends an episode, a collision still does, and the rows the rule
    never stops time out after ``max_steps`` steps; the rule's per-row data rides in ``state.info``."""
    from regrasp_mjx.envs.rollout import rollout

    _, reset_from, _ = jit_env
    problems = _rows(paper_testset, range(12))
    at_goal = jnp.arange(12)[:, None] < 6  # rows 4 and 5 start at their goal (rows 0-3 too: harmless)
    problems = problems.replace(
        start_pos=jnp.where(at_goal, problems.goal_pos, problems.start_pos),
        start_quat=jnp.where(at_goal, problems.goal_quat, problems.start_quat),
    )
    start = reset_from(problems)
    # rows 0-3 are stopped before their step 2 + row (the rule counts in info), rows 4-7 hold still
    # and are never stopped, rows 8-11 dive into the grasping tool (at the origin of e_g)
    when = jnp.where(jnp.arange(12) < 4, 2 + jnp.arange(12), 10_000)
    start = start.replace(info={**start.info, "seen": jnp.zeros(12, jnp.int32)})

    def stop(state, t, live):
        seen = state.info["seen"] + live.astype(jnp.int32)
        state = state.replace(info={**state.info, "seen": seen})
        return state, seen - 1 >= when, jnp.arange(12) % 2 == 0  # even rows count as successes

    def act(st, t):
        ee = st.pipeline_state.ee_pos
        dive = -ee / jnp.maximum(jnp.linalg.norm(ee, axis=1), 1e-9)[:, None]
        return jnp.where((jnp.arange(12) >= 8)[:, None], jnp.concatenate([dive, jnp.zeros((12, 3))], 1), 0.0)

    out = jax.tree.map(np.asarray, jax.jit(lambda s: rollout(env, act, s, max_steps=25, stop=stop))(start))
    rows = np.arange(12)
    assert out.start_valid.all()
    np.testing.assert_array_equal(out.stopped, rows < 4)
    np.testing.assert_array_equal(out.steps[:4], 2 + rows[:4])  # stopped before their step 2 + row
    np.testing.assert_array_equal(out.success, (rows < 4) & (rows % 2 == 0))  # the rule's successes alone
    assert out.time_out[4:8].all() and (out.steps[4:8] == 25).all()  # at the true goal all along: the limit
    assert out.collision[8:].all() and not out.time_out[8:].any() and (out.steps[8:] < 25).all()
    assert not (out.collision[:8].any() or out.time_out[:4].any() or out.stopped[4:].any())


def test_a_step_that_would_jump_through_the_wire_is_caught(paper_testset):
    # Steps of up to 2.5 mm: the tool at the goal (wire between the jaws) moves 2.5 mm along -y_e.
    # At the end pose jaw a has passed the wire (free); halfway it sits on the wire.
    env = RegraspEnv(EnvConfig(max_dp_mm=2.5))
    ep = _rows(paper_testset, [0]).row(0)
    ep = ep.replace(start_pos=ep.goal_pos, start_quat=ep.goal_quat)
    state = env.reset_from(ep)
    y_axis = np.asarray(g.rotation_matrix(ep.goal_quat))[:, 1]
    action = jnp.concatenate([-jnp.asarray(y_axis), jnp.zeros(3)])
    end = ep.goal_pos - 0.0025 * y_axis
    assert float(jnp.min(env.distances(ep.needle_pos, ep.needle_quat, end, ep.goal_quat))) > 0.0
    middle = ep.goal_pos - 0.00125 * y_axis
    assert float(jnp.min(env.distances(ep.needle_pos, ep.needle_quat, middle, ep.goal_quat))) < 0.0
    state = jax.jit(env.step)(state, action)
    assert float(state.metrics["collision"]) == 1.0
    assert float(state.reward) == -1.0 and float(state.done) == 1.0


def test_time_out_is_a_truncation_not_a_terminal_state(paper_testset):
    env = RegraspEnv(EnvConfig(horizon=5))
    state = env.reset_from(_rows(paper_testset, [1]).row(0))
    step = jax.jit(env.step)
    for t in range(1, 6):
        state = step(state, jnp.zeros(6))
        assert float(state.reward) == pytest.approx(-0.02)
        assert float(state.done) == (1.0 if t == 5 else 0.0)
    assert float(state.info["truncation"]) == 1.0 and float(state.metrics["time_out"]) == 1.0
    assert float(state.metrics["collision"]) == 0.0 and float(state.metrics["success"]) == 0.0


# ---- the start and goal distributions --------------------------------------------------------------
def test_sampled_starts_follow_the_spec(env, jit_env):
    reset, _, _ = jit_env
    n = 512
    state = reset(jax.random.split(jax.random.PRNGKey(7), n))
    es = state.pipeline_state
    assert np.all(np.asarray(state.metrics["reset_valid"]) == 1.0)
    assert np.all(np.asarray(state.metrics["clearance_mm"]) > 0.0)
    task = TaskConfig()
    needle = (es.needle_pos, es.needle_quat)
    start_n = g.relative(needle, (es.ee_pos, es.ee_quat))
    goal_n = g.relative(needle, (es.goal_pos, es.goal_quat))
    # Goal: alpha*, theta*, phi* fixed, d* in [6.5, 8] mm: the goal sits d* from the grasping point
    # p(4pi/3) along -x_n.
    point = np.asarray(g.needle_point(task.goal_alpha_rad))
    offset = np.asarray(goal_n[0]) - point
    depth = np.linalg.norm(offset, axis=1)
    assert np.all((depth >= 0.0065 - 1e-7) & (depth <= 0.008 + 1e-7))
    np.testing.assert_allclose(offset / depth[:, None], np.tile([-1.0, 0, 0], (n, 1)), atol=1e-5)
    # Start: 13 mm from the centre on the ray through the goal position, then +-1 mm per axis.
    nominal = 0.013 * np.asarray(goal_n[0]) / np.linalg.norm(np.asarray(goal_n[0]), axis=1, keepdims=True)
    dev = np.asarray(start_n[0]) - nominal
    assert np.abs(dev).max() <= 1e-3 + 1e-7
    assert np.abs(dev).max() > 0.9e-3  # the noise is really there
    angle = np.degrees(np.asarray(g.quat_angle(start_n[1], goal_n[1])))
    assert angle.max() <= 5.0 + 1e-3 and angle.max() > 4.0
    gap = np.linalg.norm(np.asarray(es.goal_pos - es.ee_pos), axis=1) * 1e3
    assert 3.0 < gap.mean() < 5.0  # the paper's path is 4.2 mm


def test_initial_grasp_parameters_in_range(env):
    from regrasp_mjx.world.sampling import draw_episode

    eps = jax.vmap(lambda k: draw_episode(k, TaskConfig(), 0.0054))(jax.random.split(jax.random.PRNGKey(0), 2000))
    alpha, depth, theta, phi = np.asarray(eps.grasp).T
    assert alpha.min() >= 11 * np.pi / 18 - 1e-6 and alpha.max() <= 13 * np.pi / 18 + 1e-6
    assert depth.min() >= 0.0065 - 1e-9 and depth.max() <= 0.008 + 1e-9
    assert theta.min() >= 0 and theta.max() <= 2 * np.pi + 1e-6 and theta.max() > 6.0
    assert phi.min() >= 0 and phi.max() <= 0.4 * np.pi + 1e-6
    # The needle pose is the inverse of the initial grasp: the grasp pose composed with it is e_g.
    grasp_n = g.grasp_pose(*np.asarray(eps.grasp).T)
    ident = g.compose((eps.needle_pos, eps.needle_quat), grasp_n)
    np.testing.assert_allclose(np.asarray(ident[0]), 0.0, atol=1e-7)
    np.testing.assert_allclose(np.abs(np.asarray(ident[1])[:, 0]), 1.0, atol=1e-5)


# ---- jit, vmap, determinism, brax wrappers ---------------------------------------------------------
def _rollout(env, key, n=64, steps=20):
    wrapped = AutoResetWrapper(VmapWrapper(env))

    @jax.jit
    def run(key):
        k0, k1 = jax.random.split(key)
        state = wrapped.reset(jax.random.split(k0, n))

        def body(state, k):
            state = wrapped.step(state, jax.random.uniform(k, (n, 6), minval=-1, maxval=1))
            return state, (state.obs, state.reward, state.done)

        return jax.lax.scan(body, state, jax.random.split(k1, steps))[1]

    return run(key)


def test_jit_vmap_shapes_no_nan_and_same_seed_same_rollout(env):
    obs, reward, done = _rollout(env, jax.random.PRNGKey(0))
    assert obs.shape == (20, 64, 21) and reward.shape == (20, 64) and done.shape == (20, 64)
    assert np.all(np.isfinite(np.asarray(obs)))
    q = np.asarray(obs).reshape(-1, 21)
    for k in (3, 10, 17):  # the three quaternions: unit, w >= 0
        np.testing.assert_allclose(np.linalg.norm(q[:, k : k + 4], axis=1), 1.0, atol=1e-5)
        assert np.all(q[:, k] >= 0)
    assert set(np.unique(np.asarray(reward, np.float64).round(4)).tolist()) <= {-1.0, -0.02, 1.0}
    again = _rollout(env, jax.random.PRNGKey(0))
    for a, b in zip((obs, reward, done), again):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    other = _rollout(env, jax.random.PRNGKey(1))
    assert not np.array_equal(np.asarray(obs), np.asarray(other[0]))


def test_auto_reset_restores_the_first_state(env, paper_testset):
    wrapped = AutoResetWrapper(env)
    ep = _rows(paper_testset, [2]).row(0)
    first = env.reset_from(ep)
    first.info["first_pipeline_state"] = first.pipeline_state
    first.info["first_obs"] = first.obs
    step = jax.jit(wrapped.step)
    state = first
    for _ in range(30):  # drive into the grasping tool until the episode ends
        state = step(state, jnp.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0]))
        if float(state.done):
            break
    assert float(state.done) == 1.0
    np.testing.assert_allclose(np.asarray(state.obs), np.asarray(first.obs), atol=1e-7)
    assert int(state.pipeline_state.t) == 0


def test_host_env_steps_like_the_mjx_env(env, paper_testset):
    """The CPU reference and the MJX environment give the same trajectory."""
    host = HostEnv(env.config)
    step = jax.jit(env.step)
    rng = np.random.default_rng(0)
    for row in (3, 4, 5):
        ep = _rows(paper_testset, [row]).row(0)
        state = env.reset_from(ep)
        host_obs = host.reset_from(jax.tree.map(np.asarray, ep))
        np.testing.assert_allclose(np.asarray(state.obs), host_obs, atol=2e-6)
        for _ in range(40):
            action = rng.uniform(-0.6, 0.6, 6)
            state = step(state, jnp.asarray(action, jnp.float32))
            obs, reward, done, _ = host.step(action)
            np.testing.assert_allclose(np.asarray(state.obs), obs, atol=1e-5)
            assert float(state.reward) == pytest.approx(reward)
            assert bool(state.done) == done
            if done:
                break


# ---- bad input ------------------------------------------------------------------------------------
def test_bad_actions_are_clear_errors(env, paper_testset):
    state = env.reset_from(_rows(paper_testset, [0]).row(0))
    with pytest.raises(ValueError, match=r"action has shape \(5,\); accepted: \(6,\)"):
        env.step(state, jnp.zeros(5))
    with pytest.raises(ValueError, match="floating-point"):
        env.step(state, jnp.zeros(6, jnp.int32))
    with pytest.raises(Exception, match="action has NaN or inf"):
        jax.block_until_ready(jax.jit(env.step)(state, jnp.array([0.0, jnp.nan, 0, 0, 0, 0])))


@pytest.mark.parametrize(
    "build, match",
    [
        (
            lambda: SceneConfig(jaw_angle_deg=95.0),
            r"jaw_angle_deg=95.0 is not accepted: a number of degrees in \(0, 90\)",
        ),
        (lambda: EnvConfig(horizon=0), "horizon=0 is not accepted"),
        (lambda: EnvConfig(max_dp_mm=float("nan")), "max_dp_mm=nan is not accepted"),
        (lambda: EnvConfig(step_reward=0.5), "step_reward=0.5 is not accepted"),
        (lambda: TaskConfig(init_depth_mm=(8.0, 6.5)), r"init_depth_mm=\(8.0, 6.5\) is not accepted: low <= high"),
        (lambda: TaskConfig(goal_alpha_rad=0.1), "goal_alpha_rad=0.1 is not accepted"),
    ],
)
def test_config_values_out_of_range_are_clear_errors(build, match):
    with pytest.raises(ConfigError, match=match):
        build()
