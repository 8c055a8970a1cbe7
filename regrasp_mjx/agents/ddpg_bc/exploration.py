"""The learner's exploration rollout: ``num_envs`` environments run ``horizon`` steps, each action
uniformly random with probability E_R, else the policy's (plus Gaussian ``action_noise``); the policy
sees noisy observations when the config asks for them (domain randomisation: a noise level, bias
and tool noise drawn per environment and iteration, :mod:`regrasp_mjx.envs.estimates`' noise model).

An environment that ends restarts its problem (brax's auto-reset), so every one of the
``num_envs * horizon`` transitions is valid; the first episode of each environment is recorded as a
:class:`~regrasp_mjx.envs.rollout.Rollout` (Algorithm 1's "failed episode"). The learner
(:mod:`~regrasp_mjx.agents.ddpg_bc.learner`) joins this rollout and its gradient steps in one program.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from regrasp_mjx.agents.ddpg_bc.config import TrainConfig
from regrasp_mjx.envs import estimates
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.rollout import record_step, start_outcome


def noise_levels(cfg: TrainConfig, key: jax.Array, n: int) -> dict[str, Any] | None:
    """This iteration's observation noise for ``n`` environments (``None`` without any): the bias key
    and each environment's noise level, bias and tool noise (``None`` without tool noise), all folded
    off the rollout's ``key``, so runs without noise keep their random streams."""
    if not (cfg.obs_noise_mm > 0 or cfg.obs_bias_mm > 0 or cfg.obs_tool_noise_mm > 0):
        return None
    k_sigma, k_bias_size, k_bias = jax.random.split(jax.random.fold_in(key, 17), 3)
    return {
        "k_bias": k_bias,
        "sigma": jax.random.uniform(k_sigma, (n,), maxval=cfg.obs_noise_mm),
        "bias": jax.random.uniform(k_bias_size, (n,), maxval=cfg.obs_bias_mm),
        "tool": (
            jax.random.uniform(jax.random.fold_in(key, 19), (n,), maxval=cfg.obs_tool_noise_mm)
            if cfg.obs_tool_noise_mm > 0
            else None
        ),
    }


def observe(env: RegraspEnv, state, key: jax.Array, noise: dict[str, Any] | None) -> jax.Array:
    """What the policy sees at batched ``state``: the observation of a needle estimate (a frame
    drawn by ``key``), and with tool noise the camera's view of both tools (noise-free when off)."""
    if noise is None:
        return state.obs
    es, n = state.pipeline_state, state.obs.shape[0]
    k_bias, k_frame = jax.random.split(noise["k_bias"], n), jax.random.split(key, n)
    # each environment its own frame of the tools (and its own level)
    k_tools = None if noise["tool"] is None else jax.random.split(jax.random.fold_in(key, 7), n)
    sigma, bias, tool = noise["sigma"], noise["bias"], noise["tool"]
    return estimates.estimated_observation(env, es, k_bias, k_frame, sigma, bias, tool, k_tools)


def explore(
    env: RegraspEnv, cfg: TrainConfig, policy: Callable, first, key: jax.Array, random_eps: jax.Array
) -> tuple[Any, dict[str, jax.Array], jax.Array]:
    """The rollout from the environments' ``first`` states with ``key`` (this device's):
    ``(outcome, transitions, rewards)``, transitions and rewards ``[horizon, num_envs, ...]``."""
    n = first.obs.shape[0]
    k_steps = jax.random.split(key)[1]
    noise = noise_levels(cfg, k_steps, n)

    def step(carry, k):
        state, outcome = carry
        k_coin, k_rand, k_noise = jax.random.split(k, 3)
        k_obs, k_next = jax.random.split(jax.random.fold_in(k, 17))
        explore = jax.random.uniform(k_coin, (n, 1)) < random_eps
        obs = observe(env, state, k_obs, noise)
        greedy = policy(obs)
        if cfg.action_noise > 0:
            jitter = cfg.action_noise * jax.random.normal(k_noise, greedy.shape)
            greedy = jnp.clip(greedy + jitter, -1.0, 1.0)
        action = jnp.where(
            explore,
            jax.random.uniform(k_rand, (n, env.action_size), minval=-1.0, maxval=1.0),
            greedy,
        )
        nxt = jax.vmap(env.step)(state, action)
        terminal = nxt.done * (1.0 - nxt.info["truncation"])
        transition = {
            "obs": obs,
            "action": action,
            "reward": nxt.reward,
            "next_obs": observe(env, nxt, k_next, noise),
            "terminal": terminal,
        }
        # The first episode of each environment decides Algorithm 1's "failed episode".
        first_live = ~(outcome.success | outcome.collision | outcome.time_out)
        outcome, _ = record_step(outcome, first_live, nxt, cfg.gamma**state.pipeline_state.t)
        reset = nxt.done > 0
        state = jax.tree.map(lambda f, x: jnp.where(reset.reshape((-1,) + (1,) * (x.ndim - 1)), f, x), first, nxt)
        return (state, outcome), (transition, nxt.reward)

    (_, outcome), (transitions, rewards) = jax.lax.scan(
        step, (first, start_outcome(n)), jax.random.split(k_steps, cfg.env.horizon)
    )
    return outcome, transitions, rewards
