"""The planning rollout: a policy's networks stepped through the environment until every query has
ended, with the collision shield (ours).

One jitted program per network shape, environment and entry (ego-centric or camera-frame poses,
shield on or off), cached in :data:`PLANNERS` and shared by every policy of that shape (the weights
are its first argument). With the shield, a step whose action would collide (or, given PSM bases,
leave the joint limits) takes instead the first free one of a fixed list of alternatives
(:func:`regrasp_mjx.shield.shield_candidates`), checked with the collision model the plan is
judged by; the alternatives are computed only at steps where some query's action collides.
"""

from __future__ import annotations

import types
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.agents.ddpg_bc.networks import make_networks
from regrasp_mjx.shield import SHIELD_CHUNK, shield_candidates, step_key

PLANNERS: dict[tuple, Any] = {}  # jitted planners by (hidden, members, env, camera, shield)


def members_apply(hidden: tuple[int, ...]):
    """``apply(weights, obs) -> [each member's action]``, ``weights`` one ``(params, mean, std)``
    per member. Members are unrolled (not vmapped): K is small, and exporters (jax2onnx) see plain
    dense layers."""
    nets = make_networks(6, hidden)

    def apply(weights, obs):
        return [nets.policy(p, types.SimpleNamespace(mean=m, std=s), obs) for p, m, s in weights]

    return apply


def mean_action(actions: list[jax.Array]) -> jax.Array:
    """An ensemble's action: the mean of its members' actions."""
    return sum(actions) / len(actions)


def make_planner(env_config: Any, hidden: tuple[int, ...], camera: bool, shield: bool):
    """The jitted planning program of a network shape in an environment, taking the weights
    (one ``(params, mean, std)`` per member) as its first argument: ``(weights, needle, start,
    goal, radii[, base_inv]) -> packed``; from camera-frame poses ``(weights, c_eg, c_er, c_n,
    goal_grasp, radii[, base_inv]) -> packed`` (with the camera-frame poses). ``radii`` ``[B, 2]``:
    each query's needle radius and wire radius [m]; ``goal_grasp`` ``[B, 4]``: ``(alpha*, d* [m],
    theta*, phi*)``. ``packed`` is one float32 array ``[B, ...]`` (one transfer to the host costs a
    fifth of four on a CPU, ~20 against ~100 us); :func:`unpack` splits it."""
    from regrasp_mjx import dvrk, geometry
    from regrasp_mjx.env import RegraspEnv
    from regrasp_mjx.sampling import Episode

    env = RegraspEnv(env_config)
    horizon = env.config.horizon

    apply = members_apply(tuple(hidden))

    def rollout(weights, needle, start, goal, radii, base_inv=None):
        """``base_inv`` ``[B, 4, 4]`` (optional): the inverse of each query's regrasping PSM base
        frame in e_g; the shield then also replaces actions that leave the joint limits."""
        b = needle.shape[0]

        def reach(st, rows=None):
            if base_inv is None:
                return jnp.ones(st.pipeline_state.t.shape, bool)
            es, binv = st.pipeline_state, base_inv if rows is None else base_inv[rows]
            return jax.vmap(dvrk.within_limits_jax)(binv, es.ee_pos, es.ee_quat)

        zeros = jnp.zeros((b, 4))
        episodes = Episode(
            needle[:, :3], needle[:, 3:], start[:, :3], start[:, 3:], goal[:, :3], goal[:, 3:], zeros, zeros[:, 0]
        ).replace(needle_radius=radii[:, 0], wire_radius=radii[:, 1])
        state = jax.vmap(env.reset_from)(episodes)
        valid = state.metrics["reset_valid"] > 0
        pose0 = jnp.concatenate([start[:, :3], start[:, 3:]], axis=1)
        poses = jnp.repeat(pose0[:, None], horizon + 1, axis=1)
        actions = jnp.zeros((b, horizon, 6))
        # [ended, success, collision, time_out, steps, path_mm]
        result = jnp.zeros((b, 6)).at[:, 0].set(~valid).at[:, 2].set(~valid)

        def cond(c):
            t, _, result, _, _ = c
            return (t < horizon) & jnp.any(result[:, 0] == 0)

        step = jax.vmap(env.step)

        def safer(state, t, members, a, nxt, need):
            """Replaces the actions of the rows in ``need`` (their policy action collides), a
            chunk of at most SHIELD_CHUNK rows at a time, so the work follows the colliding
            rows, not the batch; each row's alternatives depend only on its own state and t.
            ``members``: each network's actions for the whole batch (``a`` is their mean)."""
            b = a.shape[0]
            size = min(b, SHIELD_CHUNK)
            key = step_key(t)

            def chunk(c):
                a, nxt, need = c
                rows = jnp.nonzero(need, size=size, fill_value=b)[0]  # b: no row (dropped below)
                safe_rows = jnp.minimum(rows, b - 1)
                sub = jax.tree.map(lambda x: x[safe_rows], state)
                cands = shield_candidates([m[safe_rows] for m in members], a[safe_rows], key)
                tried = jax.vmap(step, in_axes=(None, 0))(sub, cands)  # [K, size, ...]
                free = (tried.metrics["collision"] == 0) & jax.vmap(lambda s: reach(s, safe_rows))(tried)
                first, cols = jnp.argmax(free, axis=0), jnp.arange(size)  # the first free candidate
                found = jnp.any(free, axis=0)
                put = lambda x, y: x.at[jnp.where(found, rows, b)].set(y[first, cols], mode="drop")  # noqa: E731
                return put(a, cands), jax.tree.map(put, nxt, tried), need.at[rows].set(False, mode="drop")

            a, nxt, _ = jax.lax.while_loop(lambda c: jnp.any(c[2]), chunk, (a, nxt, need))
            return a, nxt

        def body(c):
            t, state, result, poses, actions = c
            members = apply(weights, state.obs)
            a = mean_action(members)
            nxt = step(state, a)
            if shield:
                live_collides = ((nxt.metrics["collision"] > 0) | ~reach(nxt)) & (result[:, 0] == 0)
                # only steps where some live query's action collides pay for the alternatives
                a, nxt = jax.lax.cond(
                    jnp.any(live_collides),
                    lambda: safer(state, t, members, a, nxt, live_collides),
                    lambda: (a, nxt),
                )
            live = result[:, 0] == 0
            es = nxt.pipeline_state
            pose = jnp.concatenate([es.ee_pos, es.ee_quat], axis=1)
            # rows after the end repeat the last pose
            poses = jnp.where(live[:, None, None] & (jnp.arange(horizon + 1) > t)[None, :, None], pose[:, None], poses)
            actions = actions.at[:, t].set(jnp.where(live[:, None], jnp.clip(a, -1, 1), 0.0))
            new = jnp.stack(
                [
                    nxt.done,
                    nxt.metrics["success"],
                    nxt.metrics["collision"],
                    nxt.metrics["time_out"],
                    es.t.astype(jnp.float32),
                    nxt.metrics["path_length_mm"],
                ],
                axis=1,
            )
            result = jnp.where((live & (nxt.done > 0))[:, None], new, result)
            state = jax.tree.map(lambda x, y: jnp.where(live.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), nxt, state)
            return t + 1, state, result, poses, actions

        _, _, result, poses, actions = jax.lax.while_loop(cond, body, (jnp.int32(0), state, result, poses, actions))
        return valid, result, poses, actions

    def pack(*parts):  # each [B, ...] flattened to [B, n] (a [B] part to [B, 1])
        return jnp.concatenate([p.reshape(p.shape[0], -1).astype(jnp.float32) for p in parts], axis=1)

    def from_camera(weights, c_eg, c_er, c_n, goal_grasp, radii, base_inv=None):
        pose = lambda x: (x[:, :3], x[:, 3:])  # noqa: E731
        join = lambda p: jnp.concatenate([p[0], p[1]], axis=-1)  # noqa: E731
        eg_inv = geometry.inverse(pose(c_eg))
        needle = geometry.compose(eg_inv, pose(c_n))
        start = geometry.compose(eg_inv, pose(c_er))
        goal = join(geometry.compose(needle, goal_pose_in_needle(goal_grasp, radii[:, 0])))
        needle, start = join(needle), join(start)
        start = start.at[:, 3:].set(geometry.canonical_quat(start[:, 3:]))
        needle = needle.at[:, 3:].set(geometry.canonical_quat(needle[:, 3:]))
        valid, result, poses, actions = rollout(weights, needle, start, goal, radii, base_inv)
        cam = jax.vmap(lambda c, p: join(geometry.compose(pose(c[None]), pose(p))))(c_eg, poses)
        return pack(valid, result, poses, actions, cam)

    def ego(weights, needle, start, goal, radii, base_inv=None):
        return pack(*rollout(weights, needle, start, goal, radii, base_inv))

    return jax.jit(from_camera if camera else ego)


def unpack(packed: np.ndarray, horizon: int, camera: bool) -> tuple[np.ndarray, ...]:
    """``(valid[B], result[B, 6], poses[B, H+1, 7], actions[B, H, 6][, camera poses[B, H+1, 7]])`` of
    a planner's packed output (``result``: ended, success, collision, time-out, steps, path mm)."""
    b = packed.shape[0]
    sizes = [1, 6, (horizon + 1) * 7, horizon * 6] + ([(horizon + 1) * 7] if camera else [])
    parts = np.split(packed, np.cumsum(sizes)[:-1], axis=1)
    shapes = [(b,), (b, 6), (b, horizon + 1, 7), (b, horizon, 6), (b, horizon + 1, 7)]
    out = [p.reshape(shape) for p, shape in zip(parts, shapes)]
    out[0] = out[0] > 0
    return tuple(out)


def goal_pose_in_needle(goal_grasp: jax.Array, radius: jax.Array):
    """The goal end-effector poses ``T_n_er*`` of goal grasps ``[..., 4]`` = ``(alpha*, d* [m], theta*,
    phi*)`` on needles of ``radius`` [m] (paper eq. 3)."""
    from regrasp_mjx import geometry

    g = goal_grasp
    return geometry.grasp_pose(g[..., 0], g[..., 1], g[..., 2], g[..., 3], radius)
