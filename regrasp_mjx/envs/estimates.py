"""Needle-pose estimates (ours): the noise model of a lab's camera estimate of the needle, and what a
policy observes through it. The closed loop (:mod:`regrasp_mjx.inference.closed_loop`) acts on such
estimates; the learner and DAgger train on them (``EnvConfig``'s observation noise).

Noise model (:class:`NeedleNoise`): each frame's estimate is the true pose moved by zero-mean
Gaussian noise, ``sigma_mm`` on each axis and a rotation of ``5 sigma`` degrees (std) about a random
axis (the success test's 1 mm : 5 degree scale), after a bias fixed for the whole episode: a shift
of exactly ``bias_mm`` in a random direction and a rotation of ``5 bias`` degrees about a random
axis (a hand-eye calibration error).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

from regrasp_mjx.core import geometry
from regrasp_mjx.core.config import require_numbers
from regrasp_mjx.envs import camera_errors
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.rollout import rollout
from regrasp_mjx.world.sampling import Episode

DEG_PER_MM = camera_errors.DEG_PER_MM  # rotation noise (deg) per mm of position noise: the success test's scale


@dataclasses.dataclass(frozen=True)
class NeedleNoise:
    """Needle-pose estimate noise: ``sigma_mm`` per frame and axis (rotation ``5 sigma`` degrees),
    and a bias of ``bias_mm`` (rotation ``5 bias`` degrees) fixed per episode."""

    sigma_mm: float = 0.0
    bias_mm: float = 0.0

    def __post_init__(self) -> None:
        require_numbers(self, ("sigma_mm", "bias_mm"), lambda v: 0.0 <= v <= 10.0, "a noise level in [0, 10] mm")


def episode_bias(key: jax.Array, needle: jax.Array, bias_mm: jax.Array) -> jax.Array:
    """The true needle poses ``[B, 7]`` moved by this episode's fixed bias (see the module docstring)."""
    return camera_errors.biased(key, needle, bias_mm)


def frame_estimate(key: jax.Array, needle: jax.Array, sigma_mm: jax.Array) -> jax.Array:
    """One camera frame's estimates of needle poses ``[B, 7]`` (zero-mean Gaussian noise)."""
    return camera_errors.white(key, needle, sigma_mm)


def fuse(total: jax.Array, estimate: jax.Array, reference: jax.Array) -> jax.Array:
    """Adds an estimate ``[B, 7]`` to a running sum, its quaternion on the hemisphere of
    ``reference``'s (the mean of nearby unit quaternions, normalised, is their chordal mean)."""
    sign = jnp.where(jnp.sum(estimate[..., 3:] * reference[..., 3:], -1, keepdims=True) < 0, -1.0, 1.0)
    return total + jnp.concatenate([estimate[..., :3], sign * estimate[..., 3:]], -1)


def mean_pose(total: jax.Array, count: jax.Array) -> jax.Array:
    quat = total[..., 3:] / jnp.linalg.norm(total[..., 3:], axis=-1, keepdims=True)
    return jnp.concatenate([total[..., :3] / count, quat], -1)


def needle_estimate(k_bias: jax.Array, k_frame: jax.Array, needle: jax.Array, sigma_mm, bias_mm) -> jax.Array:
    """One frame's estimate of needle poses ``[B, 7]``: this episode's bias (``k_bias``, fixed per
    episode), then this frame's noise (``k_frame``)."""
    return frame_estimate(k_frame, episode_bias(k_bias, needle, bias_mm), sigma_mm)


def camera_view(key: jax.Array, needle: jax.Array, ee: jax.Array, tool_noise_mm) -> tuple[jax.Array, jax.Array]:
    """One camera frame of both tools (:mod:`regrasp_mjx.robot.robot_errors`' ``camera`` view): the
    needle estimate ``[B, 7]`` and this frame's view of the regrasping tool truly at ``ee``, each
    tool's pose moved by :func:`frame_estimate`'s noise of ``tool_noise_mm``, both expressed in the
    seen grasping tool's frame (so the grasping tool's noise moves the whole view, not the needle
    relative to the regrasping jaws). Rows without tool noise get ``needle`` and ``ee`` exactly."""
    k_g, k_r = jax.random.split(key)
    b = needle.shape[0]
    identity = jnp.broadcast_to(jnp.asarray(camera_errors.IDENTITY, needle.dtype), (b, 7))
    grasping, regrasping = frame_estimate(k_g, identity, tool_noise_mm), frame_estimate(k_r, ee, tool_noise_mm)
    seen_needle, seen_ee = camera_errors.in_grasping_frame(grasping, needle, regrasping)
    exact = (jnp.broadcast_to(tool_noise_mm, (b,)) == 0.0)[:, None]
    return jnp.where(exact, needle, seen_needle), jnp.where(exact, ee, seen_ee)


def seen_from(es, needle: jax.Array):
    """``es`` (an :class:`~regrasp_mjx.envs.env.EpisodeState`, batched or not) as the estimate
    ``needle`` (``[..., 7]``, the state's batch shape) shows it: the needle there, and the goal
    end-effector with it (the goal is a grasp on the needle, so a lab places it on the estimated
    needle; only a general task observes it)."""
    pos, quat = needle[..., :3], needle[..., 3:]
    goal = geometry.compose((pos, quat), geometry.inverse((es.goal_needle_pos, es.goal_needle_quat)))
    return es.replace(needle_pos=pos, needle_quat=quat, goal_pos=goal[0], goal_quat=goal[1])


def estimated_observation(
    env: RegraspEnv,
    es,
    k_bias: jax.Array,
    k_frame: jax.Array,
    sigma_mm: jax.Array,
    bias_mm: jax.Array,
    tool_mm: jax.Array | None = None,
    k_tools: jax.Array | None = None,
) -> jax.Array:
    """What a policy sees at batched states ``es`` when each row's needle is estimated with its own
    noise, each row's keys given: ``k_bias`` ``[B, 2]`` (this episode's bias), ``k_frame`` ``[B, 2]``
    (this frame's noise), ``sigma_mm`` and ``bias_mm`` ``[B]``; with ``tool_mm`` ``[B]``, the camera
    sees both tools too, each with that noise, drawn by ``k_tools`` ``[B, 2]`` (:func:`camera_view`)."""
    needle = jnp.concatenate([es.needle_pos, es.needle_quat], -1)
    seen = jax.vmap(needle_estimate)(k_bias, k_frame, needle[:, None], sigma_mm, bias_mm)[:, 0]
    if tool_mm is None:
        return jax.vmap(env.observe)(seen_from(es, seen))
    ee = jnp.concatenate([es.ee_pos, es.ee_quat], -1)
    seen, seen_ee = jax.vmap(camera_view)(k_tools, seen[:, None], ee[:, None], tool_mm)
    seen_es = seen_from(es, seen[:, 0]).replace(ee_pos=seen_ee[:, 0, :3], ee_quat=seen_ee[:, 0, 3:])
    return jax.vmap(env.observe)(seen_es)


def noisy_observation(
    env: RegraspEnv, es, keys: jax.Array, sigma_mm: jax.Array, bias_mm: jax.Array, tool_mm: jax.Array | None = None
) -> jax.Array:
    """What a policy sees at batched states ``es`` when each row's needle is estimated with its own
    noise: ``keys`` ``[B, 2]`` per row (its bias key is ``keys``' first split, fixed for the
    episode; its frame key at step ``t`` folds ``es.t`` in), ``sigma_mm`` and ``bias_mm`` ``[B]``;
    with ``tool_mm`` ``[B]``, the camera sees both tools too, each with that noise per frame
    (:func:`camera_view`; its key folds 7 into the frame key). A pure function of the state, so a
    rollout's act and trace see the same frame. The keys split, :func:`estimated_observation`."""
    split = jax.vmap(jax.random.split)(keys)
    k_frame = jax.vmap(jax.random.fold_in)(split[:, 1], es.t)
    k_tools = None if tool_mm is None else jax.vmap(jax.random.fold_in)(k_frame, jnp.full_like(es.t, 7))
    return estimated_observation(env, es, split[:, 0], k_frame, sigma_mm, bias_mm, tool_mm, k_tools)


def evaluate_noisy(
    env: RegraspEnv,
    act: Callable,
    episodes: Episode,
    key: jax.Array,
    noise_mm: float,
    bias_mm: float,
    tool_mm: float = 0.0,
):
    """A network ``act(obs) -> action`` rolled out from test-set rows, acting each step on a new
    frame of its needle estimate (no fusing, no shield: as DAgger and the learner roll out under
    noise), with sigma and bias drawn per row from U[0, ``noise_mm``] and U[0, ``bias_mm``] by
    ``key`` (and, with ``tool_mm`` > 0, the tools seen by the camera with noise drawn from
    U[0, ``tool_mm``]); judged on the true needle. Returns the :class:`~regrasp_mjx.envs.rollout.Rollout`."""
    start = jax.vmap(env.reset_from)(episodes)
    b = start.done.shape[0]
    k_rows, k_sigma, k_bias = jax.random.split(key, 3)
    keys = jax.random.split(k_rows, b)
    sigma = jax.random.uniform(k_sigma, (b,), maxval=noise_mm)
    bias = jax.random.uniform(k_bias, (b,), maxval=bias_mm)
    tool = jax.random.uniform(jax.random.fold_in(key, 7), (b,), maxval=tool_mm) if tool_mm else None
    return rollout(
        env, lambda state, t: act(noisy_observation(env, state.pipeline_state, keys, sigma, bias, tool)), start
    )
