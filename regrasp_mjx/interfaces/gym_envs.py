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

The vector environment is one jitted, vmapped program per step (:mod:`regrasp_mjx.interfaces.gym_programs`:
the step, the autoreset and the infos in one compiled call). Its autoreset mode is ``same_step`` by
default (what Stable-Baselines3 expects: an episode's last observation in ``info["final_obs"]``, the
returned one already the next episode's first; masks in ``info["_final_obs"]``), or ``next_step``
(gymnasium 1.x's default) or ``disabled``, as ``autoreset_mode`` names it (``metadata["autoreset_mode"]``
says which). ``arrays="numpy"`` (the default) returns numpy arrays, one transfer per step;
``arrays="jax"`` keeps everything on the device for learners written in JAX (actions taken as jax
arrays, observations, rewards, flags and infos returned as jax arrays, nothing waits for the step).
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium
import jax
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs.env import ACTION_SIZE
from regrasp_mjx.interfaces import registry
from regrasp_mjx.interfaces.gym_programs import ARRAYS, GOAL_SIZE, INFO_KEYS, Program, assemble, goals  # noqa: F401
from regrasp_mjx.workflows.render import SceneRenderer
from regrasp_mjx.world.sampling import Episode

AUTORESET = {
    "same_step": AutoresetMode.SAME_STEP,
    "next_step": AutoresetMode.NEXT_STEP,
    "disabled": AutoresetMode.DISABLED,
}


def gym_id(name: str) -> str:
    return f"regrasp_mjx/{name}-v0"


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


def _spaces(env: registry.RegistryEnv) -> tuple[spaces.Dict, spaces.Box]:
    box = lambda n: spaces.Box(-np.inf, np.inf, (n,), np.float32)  # noqa: E731
    obs = spaces.Dict(
        {"observation": box(env.observation_size), "achieved_goal": box(GOAL_SIZE), "desired_goal": box(GOAL_SIZE)}
    )
    return obs, spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32)


def _shape_checked(a: Any, shape: tuple[int, ...]) -> Any:
    if a.shape != shape:
        raise ValueError(
            f"action has shape {a.shape}; accepted: {shape} (dp_x, dp_y, dp_z, rot_x, rot_y, rot_z in [-1, 1])"
        )
    if not np.issubdtype(a.dtype, np.number):
        raise ValueError(f"action has dtype {a.dtype}; accepted: finite numbers in [-1, 1] (clipped)")
    return a


def _checked_actions(actions: Any, shape: tuple[int, ...]) -> np.ndarray:
    """Host actions: of ``shape``, numeric and finite (NaN and inf refused here), as float32."""
    a = _shape_checked(np.asarray(actions), shape)
    if not np.isfinite(a.min()) or not np.isfinite(a.max()):  # min and max are NaN where any is
        raise ValueError("action has NaN or inf; accepted: finite numbers in [-1, 1] (clipped)")
    return np.asarray(a, np.float32)


def _device_actions(actions: Any, shape: tuple[int, ...]) -> Any:
    """Device actions: shape and dtype checked from the array's attributes alone (nothing waits for
    the device; a NaN or inf is refused inside the compiled step, ``EnvConfig.check_actions``)."""
    return _shape_checked(actions if hasattr(actions, "dtype") else np.asarray(actions), shape)


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
        self._program = Program(self.registry_env, 1, AutoresetMode.DISABLED)
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
        f = self._program.fields(packed, reset=True)
        return _row(f), _info(f)

    def step(self, action):
        if self._carry is None:
            raise RuntimeError("call reset() before step()")
        a = _checked_actions(action, (ACTION_SIZE,))[None]
        self._carry, packed = self._program.advance(self._carry, a)
        f = self._program.fields(packed)
        return _row(f), float(f["reward"][0]), bool(f["terminated"][0]), bool(f["truncated"][0]), _info(f)

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


def _row(fields: dict) -> dict:
    return {k: fields[k][0] for k in ("observation", "achieved_goal", "desired_goal")}


def _info(fields: dict) -> dict:
    return {
        "is_success": bool(fields["success"][0]),
        **{k: (bool(fields[k][0]) if k in ("success", "collision") else float(fields[k][0])) for k in INFO_KEYS},
    }


class NeedleRegraspVectorEnv(VectorEnv):
    """``num_envs`` registered environments stepped as one jitted, vmapped program (see the module
    docstring for the autoreset modes). ``reset(options={"episodes": batch})`` starts every
    environment from a given problem (an :class:`~regrasp_mjx.world.sampling.Episode` of ``num_envs``
    rows).

    ``arrays="numpy"``: actions checked on the host (shape, numbers, finite), everything returned as
    numpy arrays (the observations and goals read-only views of the step's one transfer, as
    ``np.asarray`` of a jax array is). ``arrays="jax"``: actions taken as they are (a jax array stays
    on the device; its shape and dtype are checked, a NaN or inf is refused inside the compiled step by an
    error from JAX that holds the refusal's line, after which the environments need a ``reset``),
    everything returned as jax arrays of the same names, shapes, dtypes and values, and nothing waits
    for the step to finish."""

    def __init__(
        self,
        num_envs: int = 1,
        name: str = "NeedleRegrasp",
        config=None,
        config_overrides: dict | None = None,
        autoreset_mode: str | AutoresetMode = "same_step",
        render_mode: str | None = None,
        arrays: str = "numpy",
    ):
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs = {num_envs!r} is not accepted: an integer >= 1")
        if isinstance(autoreset_mode, str):
            if autoreset_mode not in AUTORESET:
                raise ValueError(f"autoreset_mode {autoreset_mode!r} is not accepted: one of {', '.join(AUTORESET)}")
            autoreset_mode = AUTORESET[autoreset_mode]
        if arrays not in ARRAYS:
            raise ValueError(f"arrays={arrays!r} is not accepted: one of {', '.join(ARRAYS)}")
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
        self.arrays = arrays
        self._program = Program(self.registry_env, num_envs, autoreset_mode, arrays)
        self._check = _device_actions if arrays == "jax" else _checked_actions
        self._carry = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        key = _key(self.np_random)
        if options and "episodes" in options:
            out = self._program.start_from(_episodes(options["episodes"], self.num_envs, "episodes"), key)
        else:
            out = self._program.first(key)
        self._carry, out = out
        obs, _, _, _, infos = assemble(self._program.fields(out, reset=True))
        return obs, infos

    def step(self, actions):
        if self._carry is None:
            raise RuntimeError("call reset() before step(), and again after a step that failed")
        a = self._check(actions, (self.num_envs, ACTION_SIZE))
        carry, self._carry = self._carry, None  # donated to the step: reset() again if it fails
        self._carry, out = self._program.advance(carry, a)
        return assemble(self._program.fields(out))

    def compute_reward(self, achieved_goal, desired_goal, info):
        return goal_reward(self.registry_env.env_config, achieved_goal, desired_goal, info)
