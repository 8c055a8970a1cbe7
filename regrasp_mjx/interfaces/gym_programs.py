"""The compiled programs behind the gymnasium environments (:mod:`regrasp_mjx.interfaces.gym_envs`): ``num_envs``
registered environments reset, started from given problems and stepped with the autoreset mode folded in,
each call one jitted program whose outputs are the step's named fields (observations, goals, reward,
flags, infos), all built on the device.

A program hands them back in one of two forms: as jax arrays (the vector env's ``arrays="jax"``, for
learners written in JAX: no host round trip), or packed into one byte buffer that the host reads as
numpy views (one transfer per step, no conversion on the host; :class:`Layout`).

Ended episodes restart from a pool: problems drawn ahead, ``POOL_PER_ENV`` per environment, redrawn
all at once when the next ends would use it up (a ``lax.cond``), so that a step does not sample a
whole batch of problems to keep the few that ended (sampling rejects colliding draws, and costs
about three steps). The pool is held as one ``uint32`` array of rows (:class:`Rows`: each problem's
state and goals), so that a restart is one gather rather than one per leaf of the state.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode

from regrasp_mjx.core import geometry
from regrasp_mjx.interfaces import registry

GOAL_SIZE = 7
OBS_KEYS = ("observation", "achieved_goal", "desired_goal")
INFO_KEYS = ("success", "collision", "distance_mm", "angle_deg", "clearance_mm")
FLAGS = ("terminated", "truncated", "success", "collision")  # the boolean fields
ARRAYS = ("numpy", "jax")


def goals(es) -> tuple[jax.Array, jax.Array]:
    """``achieved_goal`` and ``desired_goal`` ``[7]`` of one environment's true poses."""
    pos, quat = geometry.relative((es.ee_pos, es.ee_quat), (es.needle_pos, es.needle_quat))
    achieved = jnp.concatenate([pos * 1e3, geometry.canonical_quat(quat)])
    desired = jnp.concatenate([es.goal_needle_pos * 1e3, geometry.canonical_quat(es.goal_needle_quat)])
    return achieved, desired


class Rows:
    """A pytree whose leaves share a leading axis ``R`` as one ``uint32`` array ``[R, D]`` and back
    (32-bit leaves bitcast, booleans as 0 or 1). ``template`` is one row's tree of shapes and dtypes."""

    def __init__(self, template: Any):
        leaves, self.treedef = jax.tree.flatten(template)
        self.specs = []
        for leaf in leaves:
            dtype = np.dtype(leaf.dtype)
            if dtype != np.bool_ and dtype.itemsize != 4:
                raise TypeError(f"a leaf of dtype {dtype} cannot be a pool row; accepted: 32-bit numbers and booleans")
            self.specs.append((tuple(leaf.shape), dtype, math.prod(leaf.shape)))
        self.width = sum(w for _, _, w in self.specs)

    def encode(self, tree: Any) -> jax.Array:
        cols = []
        for x in jax.tree.leaves(tree):
            x = x.reshape(x.shape[0], -1)
            cols.append(x.astype(jnp.uint32) if x.dtype == jnp.bool_ else jax.lax.bitcast_convert_type(x, jnp.uint32))
        return jnp.concatenate(cols, axis=1)

    def decode(self, rows: jax.Array) -> Any:
        leaves, start = [], 0
        for shape, dtype, width in self.specs:
            x = rows[:, start : start + width]
            x = x != 0 if dtype == np.bool_ else jax.lax.bitcast_convert_type(x, dtype)
            leaves.append(x.reshape((rows.shape[0],) + shape))
            start += width
        return jax.tree.unflatten(self.treedef, leaves)


class Layout:
    """Where each field lies in the byte buffer of the numpy path: 32-bit fields first (vectors, then
    one number per environment), booleans last. :meth:`pack` (on the device) writes it, :meth:`read`
    (on the host) makes numpy views of it: the vectors read-only views of the transferred buffer (as
    ``np.asarray`` of a jax array is), the per-environment numbers views of one writable copy."""

    def __init__(self, specs: dict[str, Any]):
        def order(item):
            name, s = item
            return (np.dtype(s.dtype) == np.bool_, s.ndim == 1)

        self.fields, offset, self.small = [], 0, None
        for name, s in sorted(specs.items(), key=order):
            dtype = np.dtype(np.bool_ if np.dtype(s.dtype) == np.bool_ else np.float32)
            if self.small is None and s.ndim == 1:
                self.small = offset
            size = math.prod(s.shape) * dtype.itemsize
            self.fields.append((name, dtype, tuple(s.shape), offset, size))
            offset += size
        self.small = offset if self.small is None else self.small
        self.size = offset

    def pack(self, fields: dict[str, jax.Array]) -> jax.Array:
        parts = []
        for name, dtype, _, _, _ in self.fields:
            x = fields[name]
            if dtype == np.bool_:
                parts.append(x.astype(jnp.uint8).reshape(-1))
            else:
                parts.append(jax.lax.bitcast_convert_type(x.astype(jnp.float32), jnp.uint8).reshape(-1))
        return jnp.concatenate(parts)

    def read(self, packed: Any) -> dict[str, np.ndarray]:
        buf = np.asarray(packed)
        small = buf[self.small :].copy()
        out = {}
        for name, dtype, shape, offset, size in self.fields:
            src, at = (buf, offset) if offset < self.small else (small, offset - self.small)
            out[name] = src[at : at + size].view(dtype).reshape(shape)
        return out


def assemble(f: dict[str, Any]) -> tuple[dict, Any, Any, Any, dict]:
    """A step's fields as the vector env returns them: ``(obs, rewards, terminated, truncated, infos)``;
    with same-step autoreset the ended episodes' last observations and infos in ``infos["final_obs"]``
    and ``infos["final_info"]``, their mask in ``infos["_final_obs"]`` and ``infos["_final_info"]``."""
    obs = {k: f[k] for k in OBS_KEYS}
    infos = {"is_success": f.get("is_success", f["success"]), **{k: f[k] for k in INFO_KEYS}}
    if "ended" in f:
        ended = f["ended"]
        final = {k: f["final_" + k] for k in OBS_KEYS}
        infos.update({"final_obs": final, "_final_obs": ended, "final_info": dict(infos), "_final_info": ended})
    return obs, f["reward"], f["terminated"], f["truncated"], infos


class Program:
    """``num_envs`` environments stepped by one jitted program: :meth:`first` (reset), :meth:`start_from`
    (reset from given problems) and :meth:`advance` (a step with the autoreset mode folded in). Each call
    takes and returns a carry (the states, the pool, its cursor, the key, the lanes pending a reset;
    donated to the step) and returns the fields: a dict of jax arrays (``arrays="jax"``) or one packed
    byte buffer (``arrays="numpy"``) that :meth:`fields` turns into numpy views."""

    POOL_PER_ENV = 2

    def __init__(self, env: registry.RegistryEnv, num_envs: int, autoreset: AutoresetMode, arrays: str = "numpy"):
        if arrays not in ARRAYS:
            raise ValueError(f"arrays={arrays!r} is not accepted: one of {', '.join(ARRAYS)}")
        self.env, self.n, self.autoreset, self.arrays = env, num_envs, autoreset, arrays
        reset, step = jax.vmap(env.reset), jax.vmap(env.step)
        reset_from = jax.vmap(env.reset_from)
        n, size = num_envs, self.POOL_PER_ENV * num_envs
        row = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
        goal = jax.ShapeDtypeStruct((GOAL_SIZE,), jnp.float32)
        rows = Rows((row, goal, goal))

        def fields(state) -> dict[str, jax.Array]:
            achieved, desired = jax.vmap(goals)(state.data)
            truncated = state.info["truncation"] > 0
            return {
                "observation": state.obs.astype(jnp.float32),
                "achieved_goal": achieved,
                "desired_goal": desired,
                "reward": state.reward.astype(jnp.float32),
                "terminated": (state.done > 0) & ~truncated,
                "truncated": truncated,
                **{k: state.metrics[k] > 0 for k in ("success", "collision")},
                **{k: state.metrics[k].astype(jnp.float32) for k in INFO_KEYS[2:]},
            }

        def draw(key):
            state = reset(jax.random.split(key, size))
            return rows.encode((state, *jax.vmap(goals)(state.data)))

        def carry_of(state, key):
            key, k = jax.random.split(key)
            pool = draw(k) if autoreset != AutoresetMode.DISABLED else None
            return {"state": state, "pool": pool, "cursor": jnp.int32(0), "key": key, "pending": jnp.zeros(n, bool)}

        def first(key):
            key, k = jax.random.split(key)
            state = reset(jax.random.split(k, n))
            return carry_of(state, key), fields(state)

        def start_from(episodes, key):
            key, k = jax.random.split(key)
            state = reset_from(episodes, jax.random.split(k, n))
            return carry_of(state, key), fields(state)

        def restart(carry, mask):
            """The lanes of ``mask`` from the pool's next problems (the pool redrawn first if too few
            remain): the carry with its cursor moved on, the fresh states and their goals."""
            count = jnp.sum(mask, dtype=jnp.int32)

            def redraw(pool, cursor, key):
                key, k = jax.random.split(key)
                return draw(k), jnp.int32(0), key

            # only the pool's part of the carry passes through the cond (each operand costs a copy)
            pool = jax.lax.cond(
                carry["cursor"] + count > size, redraw, lambda *p: p, carry["pool"], carry["cursor"], carry["key"]
            )
            carry = {**carry, **dict(zip(("pool", "cursor", "key"), pool))}
            index = jnp.where(mask, carry["cursor"] + jnp.cumsum(mask) - 1, 0)
            fresh, achieved, desired = rows.decode(carry["pool"][index])
            return (
                {**carry, "cursor": carry["cursor"] + count},
                fresh,
                dict(zip(OBS_KEYS, (fresh.obs, achieved, desired))),
            )

        def select(mask, a, b):
            return jax.tree.map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)

        def advance(carry, actions):
            stepped = step(carry["state"], actions.astype(jnp.float32))
            out = fields(stepped)
            ended = stepped.done > 0
            if autoreset == AutoresetMode.DISABLED:
                return {**carry, "state": stepped}, out
            if autoreset == AutoresetMode.SAME_STEP:  # the next episode's first observation; the last in final_obs
                carry, fresh, first_obs = restart(carry, ended)
                last = {"final_" + k: out[k] for k in OBS_KEYS}
                out = {**out, **select(ended, first_obs, {k: out[k] for k in OBS_KEYS}), **last, "ended": ended}
                return {**carry, "state": select(ended, fresh, stepped)}, out
            # next step: a lane that ended last step starts its next episode now, ignoring its action
            pending = carry["pending"]
            carry, fresh, first_obs = restart(carry, pending)
            zero = {k: v for k, v in out.items() if k not in OBS_KEYS}
            out = select(pending, {**first_obs, **jax.tree.map(jnp.zeros_like, zero)}, out)
            return {**carry, "state": select(pending, fresh, stepped), "pending": ended & ~pending}, out

        if arrays == "jax":
            self.first, self.start_from = jax.jit(first), jax.jit(start_from)
            self.advance = jax.jit(advance, donate_argnums=(0,))
            return
        self.layouts: dict[str, Layout] = {}

        def packed(name, fn):
            """``fn`` with its fields packed; the layout follows from their shapes, set as it is traced."""

            def run(*args):
                carry, out = fn(*args)
                out = {**out, "is_success": out["success"]}
                self.layouts[name] = layout = Layout(out)
                return carry, layout.pack(out)

            return run

        self.first, self.start_from = jax.jit(packed("reset", first)), jax.jit(packed("reset", start_from))
        self.advance = jax.jit(packed("step", advance), donate_argnums=(0,))

    def fields(self, out: Any, reset: bool = False) -> dict[str, Any]:
        """A call's fields by name: the jax arrays as they are, or the packed buffer's numpy views."""
        if self.arrays == "jax":
            return out
        return self.layouts["reset" if reset else "step"].read(out)
