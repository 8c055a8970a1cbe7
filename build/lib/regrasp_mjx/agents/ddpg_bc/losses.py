"""DDPG + BC losses with the Q-filter (Nair et al., "Overcoming Exploration in Reinforcement
Learning with Demonstrations", 2018), as their reference implementation (the HER baselines fork)
weighs them:

  critic: mean (Q(s, a) - y)^2,  y = clip(r + gamma (1 - terminal) Q'(s', pi'(s')), -1/(1-gamma), 1)
  actor:  prm * (-mean Q(s, pi(s)) + action_l2 * mean pi(s)^2)
          + bc * sum_demo 1[Q(s, a_demo) > Q(s, pi(s))] |pi(s) - a_demo|^2

The target is clipped to the range any return of this task can take (rewards in [-1, 1], a
terminal +-1), as HER's ``clip_return``. Time-outs are not terminal: the target bootstraps.
Losses take the apply functions as arguments so they can be checked against hand-worked numbers.

Two additions of ours, both from TD3 (Fujimoto et al., "Addressing Function Approximation Error in
Actor-Critic Methods", 2018), off unless asked for: with several critics (``q`` returning
``[critics, B]``) the target takes their minimum and each critic regresses on it (the loss sums the
critics' mean squared errors); ``target_noise`` > 0 smooths the target policy with clipped Gaussian
noise. The actor and the Q-filter use the first critic.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

PolicyFn = Callable[[Any, jax.Array], jax.Array]
QFn = Callable[[Any, jax.Array, jax.Array], jax.Array]


def critic_loss(
    critic_params: Any,
    target_actor_params: Any,
    target_critic_params: Any,
    batch: dict[str, jax.Array],
    policy: PolicyFn,
    q: QFn,
    gamma: float,
    key: jax.Array | None = None,
    target_noise: float = 0.0,
    target_noise_clip: float = 0.5,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    next_action = policy(target_actor_params, batch["next_obs"])
    if target_noise > 0:
        noise = jnp.clip(
            target_noise * jax.random.normal(key, next_action.shape), -target_noise_clip, target_noise_clip
        )
        next_action = jnp.clip(next_action + noise, -1.0, 1.0)
    # [critics, B]: one row per critic (a single critic's [B] is one row)
    q_next = jnp.min(jnp.atleast_2d(q(target_critic_params, batch["next_obs"], next_action)), axis=0)
    target = batch["reward"] + gamma * (1.0 - batch["terminal"]) * q_next
    target = jax.lax.stop_gradient(jnp.clip(target, -1.0 / (1.0 - gamma), 1.0))
    q_sa = jnp.atleast_2d(q(critic_params, batch["obs"], batch["action"]))
    loss = jnp.sum(jnp.mean(jnp.square(q_sa - target), axis=-1))
    return loss, {"critic_loss": loss, "q": jnp.mean(q_sa[0]), "q_target": jnp.mean(target)}


def q_filter(q_demo: jax.Array, q_pi: jax.Array, is_demo: jax.Array) -> jax.Array:
    """1 for demonstration samples whose demonstrated action the critic rates above the policy's."""
    return (is_demo & (q_demo > q_pi)).astype(jnp.float32)


def actor_loss(
    actor_params: Any,
    critic_params: Any,
    batch: dict[str, jax.Array],
    is_demo: jax.Array,
    policy: PolicyFn,
    q: QFn,
    prm_coef: float,
    bc_coef: float,
    action_l2: float,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    pi = policy(actor_params, batch["obs"])
    q1 = lambda o, a: _first_critic(q(critic_params, o, a), batch["reward"])  # noqa: E731
    q_pi = q1(batch["obs"], pi)
    primary = prm_coef * (-jnp.mean(q_pi) + action_l2 * jnp.mean(jnp.square(pi)))
    keep = jax.lax.stop_gradient(q_filter(q1(batch["obs"], batch["action"]), q_pi, is_demo))
    bc = bc_coef * jnp.sum(keep * jnp.sum(jnp.square(pi - batch["action"]), axis=-1))
    loss = primary + bc
    n_demo = jnp.maximum(jnp.sum(is_demo), 1)
    return loss, {
        "actor_loss": loss,
        "primary_loss": primary,
        "bc_loss": bc,
        "q_pi": jnp.mean(q_pi),
        "q_filter_kept": jnp.sum(keep) / n_demo,
    }


def _first_critic(q_values: jax.Array, like: jax.Array) -> jax.Array:
    """The first critic's estimates ``[B]`` from one critic's ``[B]`` or several critics' ``[C, B]``."""
    return q_values if q_values.ndim == like.ndim else q_values[0]
