"""The one rollout: actions stepped through the environment, batched, until every episode has ended.

Every loop that runs whole episodes goes through :func:`rollout`: the learner's per-epoch
evaluation and distillation's (a network's actions), ``Policy.plan`` (the networks' actions, with
the collision shield as a per-step hook, recording the trajectory), the closed loop under
needle-estimate noise (the policy and its shield on the estimate, with a stopping rule in place of
the environment's ends), the replay of planner paths (given actions, recording the transitions)
and DAgger's rollouts and lookaheads. Each returns one
:class:`Rollout`: how every episode ended, by name.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.envs.env import RegraspEnv

# act(state, t) -> actions [B, 6] of a batch of environment states at step t of the rollout
Act = Callable[[Any, jax.Array], jax.Array]
# shield(state, t, action, next_state, live) -> (action, next_state): may replace a step's actions
Shield = Callable[[Any, jax.Array, jax.Array, Any, jax.Array], tuple[jax.Array, Any]]
# trace(state, action, next_state) -> a pytree of [B, ...] arrays kept for every step
Trace = Callable[[Any, jax.Array, Any], Any]
# stop(state, t, live) -> (state, stop, success): before the step at t, the rows a stopping rule ends
# there and whether each counts as a success; the state it returns is carried on (a rule may keep
# its own per-row data in state.info, e.g. a fused needle estimate)
Stop = Callable[[Any, jax.Array, jax.Array], tuple[Any, jax.Array, jax.Array]]


class Rollout(NamedTuple):
    """How each episode of a batch ended (``[B]`` arrays, jax or numpy).

    ``start_valid`` false: the start already collided (it then counts as a collision after 0
    steps). Exactly one of ``success``, ``collision``, ``time_out`` is true for an episode that
    ended; all are false only when the rollout's step limit came first. ``steps``: actions taken;
    ``path_length_mm``: the sum of the translation steps; ``discounted_return``: the rewards summed
    with the rollout's ``gamma``. ``trace``: what the rollout's ``trace`` function kept, time-major
    ``[T, B, ...]``, zeros from each episode's end on (``None`` without one)."""

    start_valid: Any
    success: Any
    collision: Any
    time_out: Any
    steps: Any
    path_length_mm: Any
    discounted_return: Any
    trace: Any = None
    stopped: Any = None  # with a stopping rule: the rows it ended (``[B]`` bool)
    state: Any = None  # the last state (each ended row's held); None where the loop narrowed (``compact``)


def rollout(
    env: RegraspEnv,
    act: Act,
    start: Any,
    *,
    max_steps: int | None = None,
    gamma: float = 0.99,
    shield: Shield | None = None,
    trace: Trace | None = None,
    compact: bool = False,
    stop: Stop | None = None,
    step: Callable[[Any, jax.Array], Any] | None = None,
) -> Rollout:
    """Steps a batch of environment states ``start`` (``jax.vmap(env.reset_from)(episodes)``, or any
    states: rows already done end where they are) with ``act`` until each episode has ended or
    ``max_steps`` (default: the horizon) were taken. An ended episode's state is held, so ``act``
    and ``shield`` may see it again; only live rows count. Jit-able and vmap-able; the loop stops as
    soon as every episode has ended.

    ``compact``: once at most 1/:data:`COMPACT` of the batch is live, the loop carries on with
    those rows only, so a few long episodes (time-outs) no longer cost the whole batch a step each
    until the horizon. Only for ``act``, ``shield`` and ``trace`` that treat each row by its own
    state and ``t`` alone (per-row data in ``state.info``, not closed over); the outcomes are the
    same.

    ``stop``: a stopping rule in place of the environment's own ends (the closed loop's: stop when
    the needle estimate says the goal is reached). Before each step it may end live rows, as
    successes or not (``Rollout.stopped``); otherwise only a collision ends an episode, reaching
    the true goal does not, and the rows still live after ``max_steps`` steps time out (the rule
    is asked once more then, at ``t = max_steps``).

    ``step``: what carries a batch's actions out (default ``jax.vmap(env.step)``; the closed loop
    under robot errors moves by the motion the arm makes, :meth:`RegraspEnv.move`)."""
    max_steps = env.config.horizon if max_steps is None else max_steps
    b = start.done.shape[0]
    step = jax.vmap(env.step) if step is None else step
    valid = start.metrics["reset_valid"] > 0
    done0 = start.done > 0
    metric = lambda name: done0 & (start.metrics[name] > 0)  # noqa: E731
    out0 = Rollout(
        start_valid=valid,
        success=metric("success") & valid,
        collision=metric("collision") | ~valid,
        time_out=metric("time_out") & valid,
        steps=start.pipeline_state.t.astype(jnp.int32),
        path_length_mm=start.metrics["path_length_mm"].astype(jnp.float32),
        discounted_return=jnp.zeros(b, jnp.float32),
        trace=None,
    )
    if stop is not None:
        out0 = out0._replace(stopped=jnp.zeros(b, bool))
    ended0 = done0 | ~valid
    buffers = None
    if trace is not None:
        example = jax.eval_shape(lambda s: trace(s, jnp.zeros((b, env.action_size)), s), start)
        length = max_steps + (stop is not None)  # a stopping rule's loop runs to t = max_steps
        buffers = jax.tree.map(lambda x: jnp.zeros((length,) + x.shape, x.dtype), example)

    def cond(c):
        t, _, ended, _, _ = c
        return ((t <= max_steps) if stop is not None else (t < max_steps)) & ~jnp.all(ended)

    def body(c):
        t, state, ended, out, buffers = c
        live = ~ended
        if stop is not None:
            state, stopping, won = stop(state, t, live)
            stopping = live & stopping
            late = live & ~stopping & (t >= max_steps)
            success, time_out = jnp.where(stopping, won, out.success), out.time_out | late
            out = out._replace(success=success, time_out=time_out, stopped=out.stopped | stopping)
            ended = ended | stopping | late
            live = ~ended
        a = act(state, t)
        # an ended row's state is held and its step dropped: it is stepped by no motion, which the
        # continuous collision test settles at once, instead of walking its action's motion (from
        # inside the wire it ended in, say: bisected to the test's budget). DAgger's lookahead, whose
        # candidates end early by the many, ran 6x faster for it (experiments/RESULTS.md, issue 47)
        nxt = step(state, jnp.where(_rows(live, a), a, jnp.zeros_like(a)) if HOLD_STILL else a)
        if shield is not None:
            a, nxt = shield(state, t, a, nxt, live)
        if buffers is not None:
            kept = trace(state, a, nxt)
            put = lambda buf, x: buf.at[t].set(jnp.where(_rows(live, x), x, jnp.zeros_like(x)))  # noqa: E731
            buffers = jax.tree.map(put, buffers, kept)
        if stop is None:
            out, now = record_step(out, live, nxt, gamma**t)
        else:  # only a collision ends an episode between the rule's stops
            now = live & (nxt.metrics["collision"] > 0)
            out = _record_collisions(out, live, now, nxt, gamma**t)
        state = jax.tree.map(lambda x, y: jnp.where(_rows(live, x), x, y), nxt, state)
        return t + 1, state, ended | now, out, buffers

    carry = (jnp.int32(0), start, ended0, out0, buffers)
    size = b // COMPACT
    if not compact or size < 1:
        _, state, _, out, buffers = jax.lax.while_loop(cond, body, carry)
        return out._replace(trace=buffers, state=state)
    # the whole batch while more than `size` rows are live, then those rows alone
    wide = lambda c: cond(c) & (jnp.sum(~c[2]) > size)  # noqa: E731
    t, state, ended, out, buffers = jax.lax.while_loop(wide, body, carry)
    rows = jnp.nonzero(~ended, size=size, fill_value=b)[0]  # b: no row (held as ended, dropped below)
    safe = jnp.minimum(rows, b - 1)
    take = lambda x: x[safe]  # noqa: E731
    narrow = (t, jax.tree.map(take, state), ended[safe] | (rows == b), jax.tree.map(take, out))
    narrow += (jax.tree.map(lambda x: x[:, safe], buffers),)
    _, _, _, sub_out, sub_buffers = jax.lax.while_loop(cond, body, narrow)
    out = jax.tree.map(lambda x, y: x.at[rows].set(y, mode="drop"), out, sub_out)
    buffers = jax.tree.map(lambda x, y: x.at[:, rows].set(y, mode="drop"), buffers, sub_buffers)
    return out._replace(trace=buffers)


HOLD_STILL = True  # ended rows are stepped by a zero action (see rollout's body; False: by their own)
COMPACT = 16  # rollout(compact=True) narrows to the live rows once at most 1/16 of the batch is left


def start_outcome(b: int) -> Rollout:
    """The outcome of ``b`` episodes that have just begun (valid starts, nothing yet)."""
    false = jnp.zeros(b, bool)
    return Rollout(jnp.ones(b, bool), false, false, false, jnp.zeros(b, jnp.int32), jnp.zeros(b), jnp.zeros(b))


def record_step(out: Rollout, live: jax.Array, nxt: Any, discount: jax.Array) -> tuple[Rollout, jax.Array]:
    """``out`` after the step into ``nxt`` of the ``live`` rows (its reward weighted by
    ``discount``); also which rows ended with it."""
    now = live & (nxt.done > 0)
    m = nxt.metrics
    out = out._replace(
        success=jnp.where(now, m["success"] > 0, out.success),
        collision=jnp.where(now, m["collision"] > 0, out.collision),
        time_out=jnp.where(now, m["time_out"] > 0, out.time_out),
        steps=jnp.where(live, nxt.pipeline_state.t, out.steps),
        path_length_mm=jnp.where(live, m["path_length_mm"], out.path_length_mm),
        discounted_return=out.discounted_return + jnp.where(live, discount * nxt.reward, 0.0),
    )
    return out, now


def _record_collisions(out: Rollout, live: jax.Array, now: jax.Array, nxt: Any, discount: jax.Array) -> Rollout:
    """``out`` after the step into ``nxt`` of the ``live`` rows under a stopping rule: the rows that
    collided (``now``) end as collisions; the environment's success and time-out do not count."""
    return out._replace(
        collision=out.collision | now,
        steps=jnp.where(live, nxt.pipeline_state.t, out.steps),
        path_length_mm=jnp.where(live, nxt.metrics["path_length_mm"], out.path_length_mm),
        discounted_return=out.discounted_return + jnp.where(live, discount * nxt.reward, 0.0),
    )


def _rows(mask: jax.Array, x: jax.Array) -> jax.Array:
    """A ``[B]`` mask shaped to broadcast against ``x`` ``[B, ...]``."""
    return mask.reshape((-1,) + (1,) * (x.ndim - 1))


def evaluate_actor(
    env: RegraspEnv, act: Callable[[jax.Array], jax.Array], episodes: Any, gamma: float = 0.99
) -> Rollout:
    """A deterministic network ``act(obs[B, O]) -> action[B, 6]`` rolled out from test-set rows."""
    start = jax.vmap(env.reset_from)(episodes)
    return rollout(env, lambda state, t: act(state.obs), start, gamma=gamma, compact=True)


def summarize(result: Any, rollout_name: str, q_start: Any = None) -> dict[str, Any]:
    """Rates and means of one pass over a test set. ``result``: a :class:`Rollout` or anything with
    its ``success``, ``collision``, ``time_out``, ``path_length_mm`` and ``steps`` (a ``Plan``);
    ``rollout_name`` says how it was planned (``bare``: the network alone, as the paper;
    ``shielded``: through the collision shield). With ``q_start`` (the critic's estimate at each
    start), also its mean over-estimation of the return the rollout got."""
    get = lambda name: np.asarray(getattr(result, name))  # noqa: E731
    ok = get("success") > 0
    out = {
        "rollout": rollout_name,
        "problems": int(ok.size),
        "success_rate": float(ok.mean()),
        "collision_rate": float((get("collision") > 0).mean()),
        "time_out_rate": float((get("time_out") > 0).mean()),
        "path_length_mm": float(get("path_length_mm")[ok].mean()) if ok.any() else None,
        "steps": float(get("steps")[ok].mean()) if ok.any() else None,
    }
    if q_start is not None:  # the critic's estimate at the starts against the return the rollouts got
        q, ret = np.asarray(q_start), get("discounted_return")
        bias = q - ret
        out["q_start"] = float(q.mean())
        out["return_start"] = float(ret.mean())
        out["q_bias"] = float(bias.mean())
        out["q_bias_failed"] = float(bias[~ok].mean()) if (~ok).any() else None
    return out
