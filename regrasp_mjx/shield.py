"""The collision shield's alternatives to a policy action (ours), shared by planning
(``regrasp_mjx.planner``, ``regrasp_mjx.lean_planner``) and distillation (``regrasp_mjx.agents.dagger``).

When the policy's action would collide, a plan takes instead the first collision-free one of a
fixed list, closest to the policy first: each ensemble member's own action (when there are
several), half the action, then the action plus Gaussian noise of std 0.25, 0.5 and 1.0 (8 draws
each, the same for every row at a step), clipped to [-1, 1].
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

SHIELD_SEED = 20211
SHIELD_NOISE = (0.25, 0.5, 1.0)  # std of the Gaussian perturbations of the policy action ...
SHIELD_PER_NOISE = 8  # ... this many of each
SHIELD_CHUNK = 64  # colliding rows of a batch shielded together


def shield_candidates(members: list[jax.Array], action: jax.Array, key: jax.Array) -> jax.Array:
    """``[K, b, 6]`` alternatives to the policy's (mean) action ``[b, 6]`` (see the module
    docstring); ``K = (members if several) + 1 + 24``."""
    own = list(members) if len(members) > 1 else []
    noise = candidate_noise(key, action.shape[-1])
    return jnp.concatenate([jnp.stack(own + [0.5 * action]), jnp.clip(action[None] + noise, -1.0, 1.0)])


def candidate_noise(key: jax.Array, action_size: int) -> jax.Array:
    """``[24, 1, action_size]``: the Gaussian perturbations added to the action at a step with
    ``key`` (``SHIELD_PER_NOISE`` draws of each std in ``SHIELD_NOISE``, the same for every row)."""
    noise = jax.random.normal(key, (len(SHIELD_NOISE) * SHIELD_PER_NOISE, 1, action_size))
    return jnp.repeat(jnp.asarray(SHIELD_NOISE), SHIELD_PER_NOISE)[:, None, None] * noise


def step_key(t: jax.Array) -> jax.Array:
    """The candidates' key at step ``t`` of a plan (the same for every query)."""
    return jax.random.fold_in(jax.random.PRNGKey(SHIELD_SEED), t)
