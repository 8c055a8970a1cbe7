"""Closed-loop regrasping under needle-pose noise: re-plan every step from the latest estimate.

A plan made once from a noisy needle pose is executed open loop against the true needle, so its
error is never corrected. A lab re-estimates the needle every camera frame and the policy is fast
enough to act on every one: each step the policy acts on the latest estimate (or on the fused
estimate of all frames so far: the needle does not move relative to the grasping tool, so the
frames can simply be averaged), and the regrasp stops when the estimate says the goal is reached.
In simulation (:func:`make_executor`) success and collision are judged on the true needle.

The needle-estimate noise model and the noisy observation are in :mod:`regrasp_mjx.estimates`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

from regrasp_mjx import geometry
from regrasp_mjx.config import ConfigError
from regrasp_mjx.env import RegraspEnv
from regrasp_mjx.estimates import episode_bias, frame_estimate, fuse, mean_pose, seen_from
from regrasp_mjx.planner import mean_action
from regrasp_mjx.sampling import Episode
from regrasp_mjx.shield import shield_rows

FRAMES = ("one", "each", "fused")  # open loop; closed loop on each frame; closed loop on the fused frames


def _with_needle(state, needle: jax.Array):
    return state.replace(pipeline_state=seen_from(state.pipeline_state, needle))


def _at_goal(env: RegraspEnv, state, needle: jax.Array, scale: float = 1.0) -> jax.Array:
    """Whether the end-effector is at the goal grasp on ``needle`` (eqs. 8, 9 on that needle), with
    the tolerances scaled by ``scale``."""
    es = state.pipeline_state
    current = geometry.relative((es.ee_pos, es.ee_quat), (needle[:, :3], needle[:, 3:]))
    dist, angle = geometry.pose_error(current, (es.goal_needle_pos, es.goal_needle_quat))
    c = env.config
    return (dist <= scale * c.success_pos_mm * 1e-3) & (angle <= scale * math.radians(c.success_rot_deg))


def choose_action(env: RegraspEnv, apply: Callable, weights, state, t: jax.Array, shield: bool, live=None):
    """The policy's action on ``state`` (whose needle is the estimate) and, with ``shield``, for
    the ``live`` rows (default all) whose action the estimate says collides, the first of the
    shield's alternatives that it says is free (:func:`regrasp_mjx.shield.shield_rows`)."""
    step = jax.vmap(env.step)
    a = mean_action(apply(weights, state.obs))
    if not shield:
        return a
    nxt = step(state, a)
    need = nxt.metrics["collision"] > 0
    need = need if live is None else need & live
    return shield_rows(step, lambda sub: apply(weights, sub.obs), state, t, a, nxt, need)[0]


def make_executor(
    env: RegraspEnv,
    apply: Callable,
    shield: bool,
    frames: str = "fused",
    shield_env: RegraspEnv | None = None,
    stop_scale: float = 1.0,
    warmup: int = 1,
):
    """``run(weights, needle, start, goal, key, sigma_mm, bias_mm, radii=None) -> dict`` (jitted):
    regrasping in simulation for ``[B, 7]`` true needle, start and goal poses (e_g frame; ``radii``
    ``[B, 2]``: each needle's radius and wire radius in metres, for a task that varies needles).
    Each step the policy acts on an estimate of the needle: with ``frames="one"`` the first frame
    held for the whole episode (a plan made once, executed open loop), ``"each"`` that step's
    frame, ``"fused"`` the mean of the frames so far (``warmup`` of them before the first step).
    ``shield_env`` (default ``env``) is what the shield checks its alternatives with, against the
    estimated needle: one with a clearance margin keeps that much away from the estimate. Returns
    per row: ``success`` (stopped at the goal of the true needle, no collision), ``collision`` (on
    the true needle), ``time_out`` (no stop within the horizon), ``stopped`` (the estimate said the
    goal was reached), ``steps`` and ``poses`` ``[B, horizon + 1, 7]``."""
    if frames not in FRAMES:
        raise ConfigError(f"frames={frames!r} is not accepted: one of {FRAMES}")
    horizon = env.config.horizon
    step = jax.vmap(env.step)
    shield_env = env if shield_env is None else shield_env
    fused = frames == "fused"

    def run(weights, needle, start, goal, key, sigma_mm, bias_mm, radii=None):
        b = needle.shape[0]
        episode = Episode.from_poses(needle, start, goal, radii)
        state = jax.vmap(env.reset_from)(episode)
        valid = state.metrics["reset_valid"] > 0
        biased = episode_bias(jax.random.fold_in(key, horizon + 1), needle, bias_mm)
        poses = jnp.repeat(start[:, None], horizon + 1, axis=1)
        # [ended, success, collision, time_out, stopped, steps]
        result = jnp.zeros((b, 6)).at[:, 0].set(~valid).at[:, 2].set(~valid)
        total = jnp.zeros((b, 7))
        if fused:  # frames before the first step: keys beyond the horizon's
            for i in range(warmup - 1):
                frame = frame_estimate(jax.random.fold_in(key, horizon + 2 + i), biased, sigma_mm)
                total = fuse(total, frame, biased)
        seen0 = warmup - 1 if fused else 0

        def cond(c):
            t, _, _, result, _ = c
            return (t <= horizon) & jnp.any(result[:, 0] == 0)

        def body(c):
            t, state, total, result, poses = c
            estimate = frame_estimate(jax.random.fold_in(key, 0 if frames == "one" else t), biased, sigma_mm)
            total = fuse(total, estimate, biased)
            seen = mean_pose(total, (t + 1 + seen0).astype(jnp.float32)) if fused else estimate
            seen_state = _with_needle(state, seen)
            live = result[:, 0] == 0
            stop = live & _at_goal(env, seen_state, seen, stop_scale)
            truly = _at_goal(env, state, needle)
            out_of_time = live & ~stop & (t >= horizon)
            ended = stop | out_of_time
            result = jnp.where(
                ended[:, None],
                jnp.stack(
                    [jnp.ones(b), (stop & truly).astype(jnp.float32), jnp.zeros(b), out_of_time, stop, jnp.full(b, t)],
                    axis=1,
                ).astype(jnp.float32),
                result,
            )
            live = live & ~ended
            seen_state = seen_state.replace(obs=jax.vmap(env.observe)(seen_state.pipeline_state))
            a = choose_action(shield_env, apply, weights, seen_state, t, shield, live)
            nxt = step(state, a)
            collided = live & (nxt.metrics["collision"] > 0)
            result = jnp.where(
                collided[:, None],
                jnp.stack([jnp.ones(b), jnp.zeros(b), jnp.ones(b), jnp.zeros(b), jnp.zeros(b), jnp.full(b, t + 1)], 1),
                result,
            )
            es = nxt.pipeline_state
            pose = jnp.concatenate([es.ee_pos, es.ee_quat], axis=1)
            poses = jnp.where(live[:, None, None] & (jnp.arange(horizon + 1) > t)[None, :, None], pose[:, None], poses)
            state = jax.tree.map(lambda x, y: jnp.where(live.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), nxt, state)
            return t + 1, state, total, result, poses

        _, _, _, result, poses = jax.lax.while_loop(cond, body, (jnp.int32(0), state, total, result, poses))
        return {
            "start_valid": valid,
            "success": result[:, 1] > 0,
            "collision": result[:, 2] > 0,
            "time_out": result[:, 3] > 0,
            "stopped": result[:, 4] > 0,
            "steps": result[:, 5].astype(jnp.int32),
            "poses": poses,
        }

    return jax.jit(run)


def make_stepper(env: RegraspEnv, apply: Callable, shield: bool, stop_scale: float = 1.0):
    """``step(weights, needle, ee, goal, t, radii=None) -> (action, next_ee, at_goal)`` (jitted,
    ``[B, 7]`` poses in e_g; ``radii`` as :func:`make_executor`'s): one closed-loop step from the
    current estimates. ``at_goal`` (within
    ``stop_scale`` of the success tolerances on the estimate) rows should stop (their action is zero
    and ``next_ee`` is ``ee``)."""

    def one(weights, needle, ee, goal, t, radii=None):
        episode = Episode.from_poses(needle, ee, goal, radii)
        state = jax.vmap(env.reset_from)(episode)
        done = _at_goal(env, state, needle, stop_scale)
        a = jnp.where(done[:, None], 0.0, choose_action(env, apply, weights, state, t, shield, ~done))
        es = jax.vmap(env.step)(state, a).pipeline_state
        nxt = jnp.where(done[:, None], ee, jnp.concatenate([es.ee_pos, es.ee_quat], axis=1))
        return jnp.clip(a, -1.0, 1.0), nxt, done

    return jax.jit(one)
