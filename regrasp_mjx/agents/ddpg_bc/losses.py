"""DDPG + BC losses with the Q-filter (Nair et al., "Overcoming Exploration in Reinforcement
Learning with Demonstrations", 2018), as their reference implementation (the HER baselines fork)
weighs them:

  critic: mean (Q(s, a) - y)^2,  y = clip(r + gamma (1 - terminal) Q'(s', pi'(s')), -1/(1-gamma), 1)
  actor:  prm * (-mean Q(s, pi(s)) + action_l2 * mean pi(s)^2)
          + bc * sum_demo 1[Q(s, a_demo) > Q(s, pi(s))] |pi(s) - a_demo|^2

The target is clipped to the range any return of this task can take (rewards in [-1, 1], a
terminal +-1), as HER's ``clip_return``. Time-outs are not terminal: the target bootstraps.
Losses take the apply functions as arguments so they can be checked against hand-worked numbers.
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
) -> tuple[jax.Array, dict[str, jax.Array]]:
    next_action = policy(target_actor_params, batch["next_obs"])
    target = batch["reward"] + gamma * (1.0 - batch["terminal"]) * q(
        target_critic_params, batch["next_obs"], next_action
    )
    target = jax.lax.stop_gradient(jnp.clip(target, -1.0 / (1.0 - gamma), 1.0))
    q_sa = q(critic_params, batch["obs"], batch["action"])
    loss = jnp.mean(jnp.square(q_sa - target))
    return loss, {"critic_loss": loss, "q": jnp.mean(q_sa), "q_target": jnp.mean(target)}


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
    q_pi = q(critic_params, batch["obs"], pi)
    primary = prm_coef * (-jnp.mean(q_pi) + action_l2 * jnp.mean(jnp.square(pi)))
    keep = jax.lax.stop_gradient(q_filter(q(critic_params, batch["obs"], batch["action"]), q_pi, is_demo))
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
