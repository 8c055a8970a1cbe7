"""One pass of a deterministic policy over given problems, batched: how each episode ended.

Used by the learner's per-epoch evaluation and by distillation; ``Policy.plan`` has its own loop
because it also records the trajectory and may shield steps.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.env import RegraspEnv
from regrasp_mjx.sampling import Episode


def evaluate_actor(
    env: RegraspEnv, act: Callable[[jax.Array], jax.Array], episodes: Episode, gamma: float = 0.99
) -> dict[str, jax.Array]:
    """Rolls ``act(obs[B, 21]) -> action[B, 6]`` out from the problems until each episode ends
    (or the horizon). Per problem: ``success``, ``collision``, ``time_out`` (0/1), ``path_length_mm``,
    ``steps`` (at the end), ``return`` (discounted by ``gamma``), and the first observation
    ``obs0``."""
    state = jax.vmap(env.reset_from)(episodes)
    n = episodes.needle_pos.shape[0]

    def step(carry, t):
        state, result, ret = carry
        nxt = jax.vmap(env.step)(state, act(state.obs))
        live = result[:, 0] == 0
        ret = ret + jnp.where(live, gamma**t * nxt.reward, 0.0)
        new = jnp.stack(
            [
                nxt.done,
                nxt.metrics["success"],
                nxt.metrics["collision"],
                nxt.metrics["time_out"],
                nxt.metrics["path_length_mm"],
                nxt.pipeline_state.t.astype(jnp.float32),
            ],
            axis=1,
        )
        result = jnp.where((live & (nxt.done > 0))[:, None], new, result)
        state = jax.tree.map(lambda a, b: jnp.where(live.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), nxt, state)
        return (state, result, ret), None

    carry0 = (state, jnp.zeros((n, 6)), jnp.zeros(n))
    (_, result, ret), _ = jax.lax.scan(step, carry0, jnp.arange(env.config.horizon, dtype=jnp.float32))
    return {
        "success": result[:, 1],
        "collision": result[:, 2],
        "time_out": result[:, 3],
        "path_length_mm": result[:, 4],
        "steps": result[:, 5],
        "return": ret,
        "obs0": state.obs,
    }


def summarize(result: dict[str, Any], rollout: str) -> dict[str, Any]:
    """Rates and means of one pass over a test set; ``rollout`` names how it was planned
    (``bare``: the network alone, as the paper; ``shielded``: through the collision shield)."""
    r = {k: np.asarray(v) for k, v in result.items()}
    ok = r["success"] > 0
    out = {
        "rollout": rollout,
        "problems": int(ok.size),
        "success_rate": float(ok.mean()),
        "collision_rate": float(r["collision"].mean()),
        "time_out_rate": float(r["time_out"].mean()),
        "path_length_mm": float(r["path_length_mm"][ok].mean()) if ok.any() else None,
        "steps": float(r["steps"][ok].mean()) if ok.any() else None,
    }
    if "q_start" in r:  # the critic's estimate at the starts against the return the rollouts got
        bias = r["q_start"] - r["return_start"]
        out["q_start"] = float(r["q_start"].mean())
        out["return_start"] = float(r["return_start"].mean())
        out["q_bias"] = float(bias.mean())
        out["q_bias_failed"] = float(bias[~ok].mean()) if (~ok).any() else None
    return out
