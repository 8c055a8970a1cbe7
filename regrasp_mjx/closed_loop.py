"""Closed-loop regrasping under needle-pose noise: re-plan every step from the latest estimate.

A plan made once from a noisy needle pose is executed open loop against the true needle, so its
error is never corrected. A lab re-estimates the needle every camera frame and the policy is fast
enough to act on every one: each step the policy acts on the latest estimate (or on the fused
estimate of all frames so far: the needle does not move relative to the grasping tool, so the
frames can simply be averaged), and the regrasp stops when the estimate says the goal is reached.
In simulation (:func:`make_executor`) success and collision are judged on the true needle.

Noise model (:class:`NeedleNoise`): each frame's estimate is the true pose moved by zero-mean
Gaussian noise, ``sigma_mm`` on each axis and a rotation of ``5 sigma`` degrees (std) about a random
axis (the success test's 1 mm : 5 degree scale), after a bias fixed for the whole episode: a shift
of exactly ``bias_mm`` in a random direction and a rotation of ``5 bias`` degrees about a random
axis (a hand-eye calibration error).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

from regrasp_mjx import geometry
from regrasp_mjx.env import RegraspEnv
from regrasp_mjx.sampling import Episode
from regrasp_mjx.shield import shield_candidates, step_key

DEG_PER_MM = 5.0  # rotation noise (deg) per mm of position noise: the success test's scale


@dataclasses.dataclass(frozen=True)
class NeedleNoise:
    """Needle-pose estimate noise: ``sigma_mm`` per frame and axis (rotation ``5 sigma`` degrees),
    and a bias of ``bias_mm`` (rotation ``5 bias`` degrees) fixed per episode."""

    sigma_mm: float = 0.0
    bias_mm: float = 0.0

    def __post_init__(self) -> None:
        for name in ("sigma_mm", "bias_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= 10.0):
                raise ValueError(f"{name}={v!r} is not accepted: a noise level in [0, 10] mm")


def _rotate(axis_key: jax.Array, angle: jax.Array, quat: jax.Array) -> jax.Array:
    axis = jax.random.normal(axis_key, quat.shape[:-1] + (3,))
    axis = axis / jnp.linalg.norm(axis, axis=-1, keepdims=True)
    return geometry.quat_mul(geometry.quat_from_rotvec(axis * angle[..., None]), quat)


def episode_bias(key: jax.Array, needle: jax.Array, bias_mm: jax.Array) -> jax.Array:
    """The true needle poses ``[B, 7]`` moved by this episode's fixed bias (see the module docstring)."""
    k_dir, k_axis = jax.random.split(key)
    direction = jax.random.normal(k_dir, needle.shape[:-1] + (3,))
    direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
    angle = jnp.full(needle.shape[:-1], jnp.radians(DEG_PER_MM * bias_mm))
    pos = needle[..., :3] + bias_mm * 1e-3 * direction
    return jnp.concatenate([pos, _rotate(k_axis, angle, needle[..., 3:])], axis=-1)


def frame_estimate(key: jax.Array, needle: jax.Array, sigma_mm: jax.Array) -> jax.Array:
    """One camera frame's estimates of needle poses ``[B, 7]`` (zero-mean Gaussian noise)."""
    k_pos, k_angle, k_axis = jax.random.split(key, 3)
    pos = needle[..., :3] + sigma_mm * 1e-3 * jax.random.normal(k_pos, needle.shape[:-1] + (3,))
    angle = jnp.radians(DEG_PER_MM * sigma_mm) * jax.random.normal(k_angle, needle.shape[:-1])
    return jnp.concatenate([pos, _rotate(k_axis, angle, needle[..., 3:])], axis=-1)


def fuse(total: jax.Array, estimate: jax.Array, reference: jax.Array) -> jax.Array:
    """Adds an estimate ``[B, 7]`` to a running sum, its quaternion on the hemisphere of
    ``reference``'s (the mean of nearby unit quaternions, normalised, is their chordal mean)."""
    sign = jnp.where(jnp.sum(estimate[..., 3:] * reference[..., 3:], -1, keepdims=True) < 0, -1.0, 1.0)
    return total + jnp.concatenate([estimate[..., :3], sign * estimate[..., 3:]], -1)


def mean_pose(total: jax.Array, count: jax.Array) -> jax.Array:
    quat = total[..., 3:] / jnp.linalg.norm(total[..., 3:], axis=-1, keepdims=True)
    return jnp.concatenate([total[..., :3] / count, quat], -1)


def _with_needle(state, needle: jax.Array):
    es = state.pipeline_state.replace(needle_pos=needle[:, :3], needle_quat=needle[:, 3:])
    return state.replace(pipeline_state=es)


def _at_goal(env: RegraspEnv, state, needle: jax.Array, scale: float = 1.0) -> jax.Array:
    """Whether the end-effector is at the goal grasp on ``needle`` (eqs. 8, 9 on that needle), with
    the tolerances scaled by ``scale``."""
    es = state.pipeline_state
    current = geometry.relative((es.ee_pos, es.ee_quat), (needle[:, :3], needle[:, 3:]))
    dist, angle = geometry.pose_error(current, (es.goal_needle_pos, es.goal_needle_quat))
    c = env.config
    return (dist <= scale * c.success_pos_mm * 1e-3) & (angle <= scale * math.radians(c.success_rot_deg))


def choose_action(env: RegraspEnv, apply: Callable, weights, state, t: jax.Array, shield: bool):
    """The policy's action on ``state`` (whose needle is the estimate) and, with ``shield``, the
    first of the shield's alternatives that the estimate says is free where the action is not."""
    from regrasp_mjx.policy import mean_action

    step = jax.vmap(env.step)
    members = apply(weights, state.obs)
    a = mean_action(members)
    if not shield:
        return a
    collides = step(state, a).metrics["collision"] > 0

    def safer():
        cands = shield_candidates(members, a, step_key(t))  # [K, B, 6]
        free = jax.vmap(step, in_axes=(None, 0))(state, cands).metrics["collision"] == 0
        first = jnp.argmax(free, axis=0)
        pick = cands[first, jnp.arange(a.shape[0])]
        return jnp.where((collides & jnp.any(free, axis=0))[:, None], pick, a)

    return jax.lax.cond(jnp.any(collides), safer, lambda: a)


def make_executor(
    env: RegraspEnv,
    apply: Callable,
    shield: bool,
    fused: bool,
    shield_env: RegraspEnv | None = None,
    stop_scale: float = 1.0,
    warmup: int = 1,
):
    """``run(weights, needle, start, goal, key, sigma_mm, bias_mm) -> dict`` (jitted): the closed
    loop in simulation for ``[B, 7]`` true needle, start and goal poses (e_g frame). ``shield_env``
    (default ``env``) is what the shield checks its alternatives with, against the estimated
    needle: one with a clearance margin keeps that much away from the estimate. Returns per
    row: ``success`` (stopped at the goal of the true needle, no collision), ``collision`` (on the
    true needle), ``time_out`` (no stop within the horizon), ``stopped`` (the estimate said the goal
    was reached), ``steps`` and ``poses`` ``[B, horizon + 1, 7]``."""
    horizon = env.config.horizon
    step = jax.vmap(env.step)
    shield_env = env if shield_env is None else shield_env

    def run(weights, needle, start, goal, key, sigma_mm, bias_mm):
        b = needle.shape[0]
        episode = Episode.from_poses(needle, start, goal)
        state = jax.vmap(env.reset_from)(episode)
        valid = state.metrics["reset_valid"] > 0
        biased = episode_bias(jax.random.fold_in(key, horizon + 1), needle, bias_mm)
        pose0 = start
        poses = jnp.repeat(pose0[:, None], horizon + 1, axis=1)
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
            estimate = frame_estimate(jax.random.fold_in(key, t), biased, sigma_mm)
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
            a = choose_action(shield_env, apply, weights, seen_state, t, shield)
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
    """``step(weights, needle, ee, goal, t) -> (action, next_ee, at_goal)`` (jitted, ``[B, 7]``
    poses in e_g): one closed-loop step from the current estimates. ``at_goal`` (within
    ``stop_scale`` of the success tolerances on the estimate) rows should stop (their action is zero
    and ``next_ee`` is ``ee``)."""

    def one(weights, needle, ee, goal, t):
        episode = Episode.from_poses(needle, ee, goal)
        state = jax.vmap(env.reset_from)(episode)
        done = _at_goal(env, state, needle, stop_scale)
        a = jnp.where(done[:, None], 0.0, choose_action(env, apply, weights, state, t, shield))
        es = jax.vmap(env.step)(state, a).pipeline_state
        nxt = jnp.where(done[:, None], ee, jnp.concatenate([es.ee_pos, es.ee_quat], axis=1))
        return jnp.clip(a, -1.0, 1.0), nxt, done

    return jax.jit(one)
