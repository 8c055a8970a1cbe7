"""The registered environments (:mod:`regrasp_mjx.interfaces.registry`) as gymnasium 1.x environments (ours,
issue 49): ``gymnasium.make("regrasp_mjx/NeedleRegrasp-v0")`` and
``gymnasium.make_vec("regrasp_mjx/NeedleRegrasp-v0", num_envs=N, vectorization_mode="vector_entry_point")``,
one id per registered name (``import regrasp_mjx`` registers them).

Observations are goal dicts, as HER expects: ``observation`` (the policy's 21 numbers, 37 for a
general task, as its view shows them), ``achieved_goal`` (the needle in the regrasping tool's frame
now, ``T_er_n``: position in mm and a unit quaternion wxyz with w >= 0) and ``desired_goal`` (the
same at the goal grasp, ``T_er*_n``). Both goals are the true poses, the ones success is judged on
(so HER's relabelled rewards are the environment's own); under a noisy variant a learner that must
not see the truth feeds only ``observation`` (and ``desired_goal``, which a lab chooses) to its policy.

The reward is :class:`~regrasp_mjx.envs.env.RegraspEnv`'s: ``success_reward`` for a step that ends within
the success tolerances (terminated), ``collision_reward`` for one not proved clear along its whole
motion (terminated), ``step_reward`` otherwise; the horizon truncates. :meth:`compute_reward`
recomputes it from goals (vectorised; a collision from ``info["collision"]``).

The vector environment is one jitted, vmapped program per step (actions in, one packed array out).
Its autoreset mode is ``same_step`` by default (what Stable-Baselines3 expects: an episode's last
observation in ``info["final_obs"]``, the returned one already the next episode's first; masks in
``info["_final_obs"]``), or ``next_step`` (gymnasium 1.x's default) or ``disabled``, as
``autoreset_mode`` names it (``metadata["autoreset_mode"]`` says which).
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from regrasp_mjx.core import geometry
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs.env import ACTION_SIZE
from regrasp_mjx.interfaces import registry
from regrasp_mjx.workflows.render import SceneRenderer
from regrasp_mjx.world.sampling import Episode

GOAL_SIZE = 7
# the per-environment numbers after the observation and both goals, in the packed step output
SCALARS = ("reward", "terminated", "truncated", "success", "collision", "distance_mm", "angle_deg", "clearance_mm")
INFO_KEYS = ("success", "collision", "distance_mm", "angle_deg", "clearance_mm")
AUTORESET = {
    "same_step": AutoresetMode.SAME_STEP,
    "next_step": AutoresetMode.NEXT_STEP,
    "disabled": AutoresetMode.DISABLED,
}


def gym_id(name: str) -> str:
    return f"regrasp_mjx/{name}-v0"


def goals(es) -> tuple[jax.Array, jax.Array]:
    """``achieved_goal`` and ``desired_goal`` ``[7]`` of one environment's true poses."""
    pos, quat = geometry.relative((es.ee_pos, es.ee_quat), (es.needle_pos, es.needle_quat))
    achieved = jnp.concatenate([pos * 1e3, geometry.canonical_quat(quat)])
    desired = jnp.concatenate([es.goal_needle_pos * 1e3, geometry.canonical_quat(es.goal_needle_quat)])
    return achieved, desired


def _collisions(info: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``info["collision"]`` as booleans of ``shape``: one info dict, a vector env's dict of arrays,
    or a sequence of dicts (Stable-Baselines3's HER passes an array of them)."""
    if info is None:
        return np.zeros(shape, bool)
    if isinstance(info, dict):
        return np.broadcast_to(np.asarray(info.get("collision", False), bool), shape)
    flags = [bool(i.get("collision", False)) if isinstance(i, dict) else False for i in np.ravel(np.asarray(info))]
    return np.asarray(flags, bool).reshape(shape)


def goal_reward(config, achieved: Any, desired: Any, info: Any = None) -> np.ndarray:
    """The environment's reward from goals ``[..., 7]`` (vectorised over leading axes), for HER:
    ``success_reward`` within ``success_pos_mm`` and ``success_rot_deg``, ``collision_reward`` where
    ``info`` says the step collided, ``step_reward`` otherwise."""
    a, d = np.asarray(achieved, np.float64), np.asarray(desired, np.float64)
    if a.shape[-1:] != (GOAL_SIZE,) or a.shape != d.shape:
        raise ValueError(f"goals have shapes {a.shape} and {d.shape}; accepted: equal shapes (..., {GOAL_SIZE})")
    distance = np.linalg.norm(a[..., :3] - d[..., :3], axis=-1)
    cos = np.abs(np.sum(a[..., 3:] * d[..., 3:], axis=-1)) / (
        np.linalg.norm(a[..., 3:], axis=-1) * np.linalg.norm(d[..., 3:], axis=-1)
    )
    angle = 2.0 * np.arccos(np.clip(cos, 0.0, 1.0))
    success = (distance <= config.success_pos_mm) & (angle <= math.radians(config.success_rot_deg))
    reward = np.where(success, config.success_reward, config.step_reward)
    return np.where(_collisions(info, distance.shape), config.collision_reward, reward).astype(np.float32)


class _Program:
    """``num_envs`` environments stepped by one jitted program: reset, reset from given problems,
    and a step with the autoreset mode folded in. Each call takes and returns a carry (the states,
    a pool of fresh problems, the key, the lanes pending a reset) and returns one packed array ``[N, K]``.

    Ended episodes restart from the pool: problems drawn ahead, ``POOL_PER_ENV`` per environment,
    redrawn all at once when the next ends would use it up (a ``lax.cond``), so that a step does not
    sample a whole batch of problems to keep the few that ended (sampling rejects colliding draws,
    and costs about three steps)."""

    POOL_PER_ENV = 2

    def __init__(self, env: registry.RegistryEnv, num_envs: int, autoreset: AutoresetMode):
        self.env, self.n, self.autoreset = env, num_envs, autoreset
        self.obs_size = env.observation_size
        reset, step = jax.vmap(env.reset), jax.vmap(env.step)
        reset_from = jax.vmap(env.reset_from)
        n, size = num_envs, self.POOL_PER_ENV * num_envs

        def pack(state) -> jax.Array:
            achieved, desired = jax.vmap(goals)(state.data)
            flags = (state.done > 0) & (state.info["truncation"] == 0)
            cols = [state.reward, flags, state.info["truncation"]] + [state.metrics[k] for k in INFO_KEYS]
            return jnp.concatenate(
                [state.obs, achieved, desired, jnp.stack([c.astype(jnp.float32) for c in cols], -1)], -1
            )

        def select(mask, a, b):
            return jax.tree.map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)

        def carry_of(state, key):
            key, k = jax.random.split(key)
            pool = reset(jax.random.split(k, size)) if autoreset != AutoresetMode.DISABLED else None
            return {"state": state, "pool": pool, "cursor": jnp.int32(0), "key": key, "pending": jnp.zeros(n, bool)}

        def first(key):
            key, k = jax.random.split(key)
            state = reset(jax.random.split(k, n))
            return carry_of(state, key), pack(state)

        def start_from(episodes, key):
            key, k = jax.random.split(key)
            state = reset_from(episodes, jax.random.split(k, n))
            return carry_of(state, key), pack(state)

        def restart(carry, mask):
            """The lanes of ``mask`` from the pool's next problems (the pool redrawn first if too few remain)."""
            count = jnp.sum(mask, dtype=jnp.int32)

            def redraw(c):
                key, k = jax.random.split(c["key"])
                return {**c, "pool": reset(jax.random.split(k, size)), "cursor": jnp.int32(0), "key": key}

            carry = jax.lax.cond(carry["cursor"] + count > size, redraw, lambda c: c, carry)
            index = jnp.where(mask, carry["cursor"] + jnp.cumsum(mask) - 1, 0)
            fresh = jax.tree.map(lambda x: x[index], carry["pool"])
            return {**carry, "cursor": carry["cursor"] + count}, fresh

        def advance(carry, actions):
            stepped = step(carry["state"], actions)
            out = pack(stepped)
            ended = stepped.done > 0
            if autoreset == AutoresetMode.DISABLED:
                return {**carry, "state": stepped}, out
            if autoreset == AutoresetMode.SAME_STEP:  # the next episode's first observation; the last in final_obs
                carry, fresh = restart(carry, ended)
                obs = jnp.where(ended[:, None], pack(fresh), out)
                width = self.obs_size + 2 * GOAL_SIZE
                packed = jnp.concatenate([obs[:, :width], out[:, width:], out[:, :width]], -1)
                return {**carry, "state": select(ended, fresh, stepped)}, packed
            # next step: a lane that ended last step starts its next episode now, ignoring its action
            pending = carry["pending"]
            carry, fresh = restart(carry, pending)
            out = jnp.where(pending[:, None], pack(fresh).at[:, -len(SCALARS) :].set(0.0), out)
            return {**carry, "state": select(pending, fresh, stepped), "pending": ended & ~pending}, out

        self.first = jax.jit(first)
        self.start_from = jax.jit(start_from)
        self.advance = jax.jit(advance, donate_argnums=(0,))

    def unpack(self, packed: np.ndarray) -> tuple[dict, dict[str, np.ndarray], dict | None]:
        """The observation dict, the scalars by name and (same-step autoreset) the final observations."""
        o = self.obs_size
        obs = {
            "observation": packed[:, :o],
            "achieved_goal": packed[:, o : o + GOAL_SIZE],
            "desired_goal": packed[:, o + GOAL_SIZE : o + 2 * GOAL_SIZE],
        }
        k = o + 2 * GOAL_SIZE
        scalars = {name: packed[:, k + i] for i, name in enumerate(SCALARS)}
        final = None
        if packed.shape[1] > k + len(SCALARS):
            f = packed[:, k + len(SCALARS) :]
            final = {
                "observation": f[:, :o],
                "achieved_goal": f[:, o : o + GOAL_SIZE],
                "desired_goal": f[:, o + GOAL_SIZE :],
            }
        return obs, scalars, final


def _spaces(env: registry.RegistryEnv) -> tuple[spaces.Dict, spaces.Box]:
    box = lambda n: spaces.Box(-np.inf, np.inf, (n,), np.float32)  # noqa: E731
    obs = spaces.Dict(
        {"observation": box(env.observation_size), "achieved_goal": box(GOAL_SIZE), "desired_goal": box(GOAL_SIZE)}
    )
    return obs, spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32)


def _checked_actions(actions: Any, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(actions)
    if a.shape != shape:
        raise ValueError(
            f"action has shape {a.shape}; accepted: {shape} (dp_x, dp_y, dp_z, rot_x, rot_y, rot_z in [-1, 1])"
        )
    if not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
        raise ValueError("action has NaN, inf or is not numeric; accepted: finite numbers in [-1, 1] (clipped)")
    return a.astype(np.float32)


def _episodes(episodes: Any, n: int, key: str) -> Episode:
    """``options[key]``, an :class:`Episode` of ``n`` rows, or a ConfigError naming it."""
    accepted = f"an Episode of {n} rows, e.g. load_testset('paper300')[0].row(i) with a leading axis of 1"
    if not isinstance(episodes, Episode):
        raise ConfigError(f"options[{key!r}]={episodes!r:.60} is not accepted: {accepted}")
    lead = {(np.shape(x) or (None,))[0] for x in jax.tree.leaves(episodes)}
    if lead != {n}:
        raise ConfigError(f"options[{key!r}] has rows {sorted(lead, key=str)}; accepted: {accepted}")
    return episodes


def _key(np_random: np.random.Generator) -> jax.Array:
    return jax.random.PRNGKey(int(np_random.integers(2**31)))


class NeedleRegraspEnv(gymnasium.Env):
    """One registered environment (``name``, its ``config`` and ``config_overrides`` as
    :func:`regrasp_mjx.interfaces.registry.load` takes them) as a gymnasium goal environment.

    ``reset(seed=..., options={"episode": row})`` starts from a given problem (an
    :class:`~regrasp_mjx.world.sampling.Episode` of one row, e.g. ``load_testset("paper300")[0].row(i)``
    with a leading axis of 1). ``render_mode="rgb_array"``: :meth:`render` draws the true scene.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        name: str = "NeedleRegrasp",
        config=None,
        config_overrides: dict | None = None,
        render_mode: str | None = None,
        width: int = 320,
        height: int = 240,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r} is not accepted: None or 'rgb_array'")
        self.registry_env = registry.load(name, config, config_overrides)
        self.observation_space, self.action_space = _spaces(self.registry_env)
        self.render_mode, self.width, self.height = render_mode, width, height
        self._program = _Program(self.registry_env, 1, AutoresetMode.DISABLED)
        self._carry = None
        self._renderer = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        key = _key(self.np_random)
        if options and "episode" in options:
            out = self._program.start_from(_episodes(options["episode"], 1, "episode"), key)
        else:
            out = self._program.first(key)
        self._carry, packed = out
        obs, scalars, _ = self._program.unpack(np.asarray(packed))
        return _row(obs), _info(scalars, 0)

    def step(self, action):
        if self._carry is None:
            raise RuntimeError("call reset() before step()")
        a = _checked_actions(action, (ACTION_SIZE,))[None]
        self._carry, packed = self._program.advance(self._carry, a)
        obs, s, _ = self._program.unpack(np.asarray(packed))
        return _row(obs), float(s["reward"][0]), bool(s["terminated"][0]), bool(s["truncated"][0]), _info(s, 0)

    def compute_reward(self, achieved_goal, desired_goal, info):
        return goal_reward(self.registry_env.env_config, achieved_goal, desired_goal, info)

    def render(self):
        if self.render_mode is None or self._carry is None:
            return None
        if self._renderer is None:
            self._renderer = SceneRenderer(self.registry_env.env.scene, self.width, self.height)
        es = jax.tree.map(lambda x: np.asarray(x)[0], self._carry["state"].data)
        pose = lambda p, q: np.concatenate([p, q])  # noqa: E731
        return self._renderer.image(
            pose(es.needle_pos, es.needle_quat), pose(es.ee_pos, es.ee_quat), pose(es.goal_pos, es.goal_quat)
        )

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _row(obs: dict) -> dict:
    return {k: v[0] for k, v in obs.items()}


def _info(scalars: dict, i: int) -> dict:
    return {
        "is_success": bool(scalars["success"][i]),
        **{k: (bool(scalars[k][i]) if k in ("success", "collision") else float(scalars[k][i])) for k in INFO_KEYS},
    }


class NeedleRegraspVectorEnv(VectorEnv):
    """``num_envs`` registered environments stepped as one jitted, vmapped program (see the module
    docstring for the autoreset modes). ``reset(options={"episodes": batch})`` starts every
    environment from a given problem (an :class:`~regrasp_mjx.world.sampling.Episode` of ``num_envs``
    rows)."""

    def __init__(
        self,
        num_envs: int = 1,
        name: str = "NeedleRegrasp",
        config=None,
        config_overrides: dict | None = None,
        autoreset_mode: str | AutoresetMode = "same_step",
        render_mode: str | None = None,
    ):
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs = {num_envs!r} is not accepted: an integer >= 1")
        if isinstance(autoreset_mode, str):
            if autoreset_mode not in AUTORESET:
                raise ValueError(f"autoreset_mode {autoreset_mode!r} is not accepted: one of {', '.join(AUTORESET)}")
            autoreset_mode = AUTORESET[autoreset_mode]
        if render_mode is not None:
            raise ValueError(
                "the vector environment does not render; accepted: render_mode=None (the single one draws)"
            )
        self.registry_env = registry.load(name, config, config_overrides)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = _spaces(self.registry_env)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.metadata = {"autoreset_mode": autoreset_mode}
        self.render_mode = None
        self._program = _Program(self.registry_env, num_envs, autoreset_mode)
        self._carry = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        key = _key(self.np_random)
        if options and "episodes" in options:
            out = self._program.start_from(_episodes(options["episodes"], self.num_envs, "episodes"), key)
        else:
            out = self._program.first(key)
        self._carry, packed = out
        obs, scalars, _ = self._program.unpack(np.asarray(packed))
        return obs, self._infos(scalars)

    def step(self, actions):
        if self._carry is None:
            raise RuntimeError("call reset() before step()")
        a = _checked_actions(actions, (self.num_envs, ACTION_SIZE))
        self._carry, packed = self._program.advance(self._carry, a)
        obs, s, final = self._program.unpack(np.asarray(packed))
        terminated, truncated = s["terminated"] > 0, s["truncated"] > 0
        infos = self._infos(s)
        if final is not None:
            ended = terminated | truncated
            infos.update({"final_obs": final, "_final_obs": ended, "final_info": dict(infos), "_final_info": ended})
        return obs, s["reward"].copy(), terminated, truncated, infos

    def _infos(self, s: dict) -> dict:
        return {
            "is_success": s["success"] > 0,
            **{k: s[k] > 0 if k in ("success", "collision") else s[k] for k in INFO_KEYS},
        }

    def compute_reward(self, achieved_goal, desired_goal, info):
        return goal_reward(self.registry_env.env_config, achieved_goal, desired_goal, info)
