"""The collision shield (ours): its alternatives to a policy action and the one batched
implementation that picks among them, shared by planning (``regrasp_mjx.inference.planner``; the one-query
``regrasp_mjx.inference.lean_planner`` follows it in numba), the closed loop (``regrasp_mjx.inference.closed_loop``)
and distillation (``regrasp_mjx.agents.dagger``).

When the policy's action would collide, a step takes instead the first collision-free one of a
fixed list, closest to the policy first: each ensemble member's own action (when there are
several), half the action, then the action plus Gaussian noise of std 0.25, 0.5 and 1.0 (8 draws
each, the same for every row at a step), clipped to [-1, 1]. When none is free, the action stays.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

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


def shield_rows(
    step: Callable[[Any, jax.Array], Any],
    members_of: Callable[[Any], list[jax.Array]],
    state: Any,
    t: jax.Array,
    action: jax.Array,
    nxt: Any,
    need: jax.Array,
    allowed: Callable[[Any, jax.Array], jax.Array] | None = None,
    chunk: int = SHIELD_CHUNK,
) -> tuple[jax.Array, Any]:
    """``(action, nxt)`` with the rows in ``need`` (``[B]``: their action collides) replaced by
    their first free alternative and the state it steps into.

    ``step(states, actions)``: the batched step whose collision test the shield trusts (the
    environment, or one with a clearance margin or the estimated needle); ``members_of(states)``:
    each ensemble member's actions at some rows of ``state``; ``nxt``: ``step(state, action)``;
    ``allowed(states, rows)`` (optional): which stepped states are also acceptable (e.g. within the
    joint limits), ``rows`` their indices in the batch. Jit-able. The alternatives are computed
    only when some row needs them, ``chunk`` rows at a time, so the work follows the colliding rows,
    not the batch; a row's choice depends only on its own state and ``t``, never on its batch."""
    b = action.shape[0]
    size = min(b, chunk)
    key = step_key(t)

    def one_chunk(c):
        action, nxt, need = c
        rows = jnp.nonzero(need, size=size, fill_value=b)[0]  # b: no row (dropped below)
        safe = jnp.minimum(rows, b - 1)
        sub = jax.tree.map(lambda x: x[safe], state)
        cands = shield_candidates(members_of(sub), action[safe], key)  # [K, size, 6]
        tried = jax.vmap(step, in_axes=(None, 0))(sub, cands)
        free = tried.metrics["collision"] == 0
        if allowed is not None:
            free = free & jax.vmap(lambda s: allowed(s, safe))(tried)
        first, cols = jnp.argmax(free, axis=0), jnp.arange(size)  # the first free alternative
        put_rows = jnp.where(jnp.any(free, axis=0), rows, b)
        put = lambda x, y: x.at[put_rows].set(y[first, cols], mode="drop")  # noqa: E731
        return put(action, cands), jax.tree.map(put, nxt, tried), need.at[rows].set(False, mode="drop")

    def shielded():
        out = jax.lax.while_loop(lambda c: jnp.any(c[2]), one_chunk, (action, nxt, need))
        return out[0], out[1]

    return jax.lax.cond(jnp.any(need), shielded, lambda: (action, nxt))
