"""The one batched shield (``regrasp_mjx.envs.shield.shield_rows``) that planning and the closed loop share:
against a brute-force choice over every alternative of every row, for any chunk size."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.shield import shield_candidates, shield_rows, step_key
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.world.sampling import load_testset


@pytest.fixture(scope="module")
def batch():
    policy = load_policy("default")
    env = RegraspEnv(policy.env_config)
    episodes = jax.tree.map(lambda x: x[:16], load_testset("paper300")[0])
    state = jax.tree.map(jnp.asarray, jax.vmap(env.reset_from)(episodes))  # device arrays throughout
    # large random actions: some collide, and the alternatives around them differ from row to row
    action = jnp.asarray(np.random.default_rng(0).uniform(-1.0, 1.0, (16, 6)), jnp.float32)
    return policy, jax.vmap(env.step), state, action


@pytest.mark.slow
def test_shield_rows_takes_each_rows_first_free_allowed_alternative_in_any_chunk(batch):
    policy, step, state, action = batch
    members = lambda sub: policy.members_fn()(sub.obs)  # noqa: E731
    t = jnp.int32(3)
    start_x = state.pipeline_state.ee_pos[:, 0]
    # also acceptable only where the tool moved along +x: the first free alternative is often not the first
    allowed = lambda st, rows: st.pipeline_state.ee_pos[:, 0] > start_x[rows]  # noqa: E731
    need = jnp.arange(16) % 4 != 1  # every fourth row keeps its action whatever it does
    nxt = step(state, action)

    cands = shield_candidates(members(state), action, step_key(t))  # [K, 16, 6], brute force
    tried = jax.vmap(step, in_axes=(None, 0))(state, cands)
    free = np.asarray((tried.metrics["collision"] == 0) & (tried.pipeline_state.ee_pos[..., 0] > start_x))
    first = free.argmax(axis=0)
    take = np.asarray(need) & free.any(axis=0)
    expected = np.where(take[:, None], np.asarray(cands)[first, np.arange(16)], np.asarray(action))
    assert take.sum() >= 6 and (first[take] > 0).sum() >= 2  # the case is not trivial

    for chunk in (3, 16, 64):
        a, n = jax.jit(lambda s, a, n, need, c=chunk: shield_rows(step, members, s, t, a, n, need, allowed, c))(
            state, action, nxt, need
        )
        np.testing.assert_array_equal(np.asarray(a), expected)
        again = step(state, a)  # the returned states are where the returned actions lead
        np.testing.assert_allclose(
            np.asarray(n.pipeline_state.ee_pos), np.asarray(again.pipeline_state.ee_pos), atol=1e-7
        )
    # nothing needed: nothing changes, and no alternative is computed
    a, n = shield_rows(step, members, state, t, action, nxt, jnp.zeros(16, bool))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(action))


@pytest.mark.slow
def test_the_closed_loop_shields_colliding_rows_with_shield_rows():
    """The closed loop's action choice: the network's action where it is free; where it collides,
    shield_rows' choice, which steps clear of the needle and the other tool."""
    from regrasp_mjx.inference.closed_loop import choose_action

    policy = load_policy("default")
    env = RegraspEnv(policy.env_config)
    step = jax.vmap(env.step)
    # a stand-in network, a function of the observation alone: full-scale actions in fixed directions
    w = jnp.asarray(np.random.default_rng(1).normal(size=(policy.obs_size, 6)), jnp.float32)
    net = lambda weights, obs: [jnp.sign(obs @ w)]  # noqa: E731
    state = jax.tree.map(jnp.asarray, jax.vmap(env.reset_from)(load_testset("paper300")[0]))
    hits = np.asarray(step(state, net(None, state.obs)[0]).metrics["collision"] > 0)
    rows = np.r_[np.flatnonzero(hits)[:6], np.flatnonzero(~hits)[:10]]  # 6 colliding rows of paper300 (11 in all)
    state = jax.tree.map(lambda x: x[rows], state)
    t = jnp.int32(0)
    bare = choose_action(env, net, None, state, t, shield=False)
    a = choose_action(env, net, None, state, t, shield=True)
    need = np.asarray(step(state, bare).metrics["collision"] > 0)
    assert need.sum() == 6
    np.testing.assert_array_equal(np.asarray(a)[~need], np.asarray(bare)[~need])
    assert not np.asarray(step(state, a).metrics["collision"] > 0).any()  # every colliding row found a free one
    ref, _ = shield_rows(step, lambda s: net(None, s.obs), state, t, bare, step(state, bare), jnp.asarray(need))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(ref))
