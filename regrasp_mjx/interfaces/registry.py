"""Environments by name, as MuJoCo Playground loads its tasks (ours, issue 49):
``load(name, config=None, config_overrides=None)`` returns an environment with Playground's
``MjxEnv`` interface, ``reset(rng) -> State`` and ``step(state, action) -> State`` (pure,
jit/vmap-able), ``observation_size``, ``action_size``, ``mj_model`` and ``mjx_model``, and
``default_config(name)`` its config (an ``ml_collections.ConfigDict``).

Each name is :class:`~regrasp_mjx.envs.env.RegraspEnv` (the same reward, success, collision test and
observation) seen through one of the error models a lab has (:data:`ENVS`):

- ``exact``: the policy sees the true poses, or the needle through its estimate's noise
  (:mod:`regrasp_mjx.envs.estimates`: a new frame each step, a bias fixed per episode);
- ``kinematic``: each tool where its arm's kinematics put it through a camera-to-base calibration
  that is off (:mod:`regrasp_mjx.robot.robot_errors`), the needle from the camera;
- ``camera``: both tools and the needle from the camera, each with its tracking noise (the
  calibration cancels).

Where a view shows the tool off its true pose, the action (a motion in the view) is carried out as
the arm would, turned by the view's orientation error (``robot_errors.executed``; joint offsets are
not modelled here). Success and collisions are always judged on the true poses. Each episode draws
its error sizes from ``U[0, value]`` (``errors.randomise``, what a learner trains on) or takes them
exactly (an evaluation's condition).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
from brax.envs.base import State as BraxState
from flax import struct
from ml_collections import config_dict

from regrasp_mjx.core.config import TASKS, ConfigError, EnvConfig, is_number, require
from regrasp_mjx.core.config_text import env_config_from_dict
from regrasp_mjx.envs import estimates
from regrasp_mjx.envs.env import EpisodeState, RegraspEnv
from regrasp_mjx.robot import robot_errors
from regrasp_mjx.workflows.render import SceneRenderer
from regrasp_mjx.world.sampling import Episode

VIEWS = ("exact", "kinematic", "camera")
ERROR_SIZES = ("needle_sigma_mm", "needle_bias_mm", "tool_noise_mm", "calibration_mm", "calibration_deg")
MAX_ERRORS = {
    "needle_sigma_mm": 10.0,
    "needle_bias_mm": 10.0,
    "tool_noise_mm": robot_errors.MAX_TOOL_NOISE_MM,
    "calibration_mm": robot_errors.MAX_CALIBRATION_MM,
    "calibration_deg": robot_errors.MAX_CALIBRATION_DEG,
}


@dataclasses.dataclass(frozen=True)
class Variant:
    """A registered environment: the task (``config.TASKS``), the view and its error sizes."""

    task: str
    view: str = "exact"
    needle_sigma_mm: float = 0.0
    needle_bias_mm: float = 0.0
    tool_noise_mm: float = 0.0
    calibration_mm: float = 0.0
    calibration_deg: float = 0.0
    about: str = ""


ENVS = {
    "NeedleRegrasp": Variant("paper", about="the paper's task, true poses (SPEC's MDP)"),
    "NeedleRegraspGeneral": Variant(
        "general", about="the general task: any goal grasp and needle in config.GENERAL_TASK's ranges"
    ),
    "NeedleRegraspNoisy": Variant(
        "paper",
        needle_sigma_mm=0.5,
        needle_bias_mm=0.25,
        about="the needle through its estimate: sigma U[0, 0.5] mm per frame, bias U[0, 0.25] mm "
        "(the shipped default's training)",
    ),
    "NeedleRegraspCalibration": Variant(
        "paper",
        view="kinematic",
        needle_sigma_mm=0.25,
        calibration_mm=5.0,
        calibration_deg=3.0,
        about="the tools from their arms' kinematics through a calibration off by U[0, 5] mm and U[0, 3] deg per arm",
    ),
    "NeedleRegraspCamera": Variant(
        "paper",
        view="camera",
        needle_sigma_mm=0.25,
        tool_noise_mm=0.25,
        about="both tools and the needle from the camera, tracking noise U[0, 0.25] mm (calibration cancels)",
    ),
}


@struct.dataclass
class State:
    """Playground's ``mjx_env.State``: ``data`` is the episode's :class:`~regrasp_mjx.envs.env.EpisodeState`
    (true poses); ``info`` holds ``truncation`` and the episode's error draws (``errors``,
    ``noise_key``, ``arms``)."""

    data: EpisodeState
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    metrics: dict[str, jax.Array]
    info: dict[str, Any]


def _check_name(name: str) -> Variant:
    if name not in ENVS:
        raise ValueError(f"no environment {name!r}; registered: {', '.join(ENVS)}")
    return ENVS[name]


def default_config(name: str) -> config_dict.ConfigDict:
    """``name``'s config: ``env`` (an :class:`~regrasp_mjx.core.config.EnvConfig` as nested fields) and
    ``errors`` (``view``, the five error sizes, ``randomise``)."""
    v = _check_name(name)
    env = dataclasses.asdict(EnvConfig(task=TASKS[v.task]))
    errors = {"view": v.view, **{k: float(getattr(v, k)) for k in ERROR_SIZES}, "randomise": True}
    return config_dict.ConfigDict({"env": env, "errors": errors})


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    """A nested dict as one level of dotted keys (``{"env": {"horizon": 80}}`` -> ``{"env.horizon": 80}``)."""
    out = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def load(name: str, config: config_dict.ConfigDict | dict | None = None, config_overrides: dict | None = None):
    """The environment ``name`` (:data:`ENVS`) with ``config`` (default: :func:`default_config`) and
    ``config_overrides`` (dotted keys, e.g. ``{"env.horizon": 80, "errors.needle_sigma_mm": 0.1}``)
    applied; Playground's ``registry.load`` signature."""
    _check_name(name)
    require(
        config is None or isinstance(config, (dict, config_dict.ConfigDict)),
        "config",
        config,
        "None, a dict or an ml_collections ConfigDict (of default_config(name)'s keys)",
    )
    require(
        config_overrides is None or isinstance(config_overrides, dict),
        "config_overrides",
        config_overrides,
        'None or a dict of dotted keys, e.g. {"env.horizon": 80}',
    )
    cfg = default_config(name)
    given = config.to_dict() if isinstance(config, config_dict.ConfigDict) else (config or {})
    overrides = {**_flatten(given), **(config_overrides or {})}
    accepted = list(_flatten(cfg.to_dict()))
    for key in overrides:
        if key not in accepted:
            raise ConfigError(f"{name} has no config key {key!r}; accepted: {', '.join(accepted)}")
    try:
        cfg.update_from_flattened_dict(dict(overrides))
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{name}: a config value is not accepted ({err})") from err
    return RegistryEnv(name, cfg)


class RegistryEnv:
    """One registered environment (see the module docstring); :func:`load` makes it."""

    def __init__(self, name: str, config: config_dict.ConfigDict):
        self.name = name
        self._config = config
        self.env = RegraspEnv(env_config_from_dict(config.env.to_dict()))
        errors = config.errors
        if errors.view not in VIEWS:
            raise ConfigError(f"errors.view = {errors.view!r} is not accepted: one of {', '.join(VIEWS)}")
        for k in ERROR_SIZES:
            v = errors[k]
            if not (is_number(v) and 0.0 <= v <= MAX_ERRORS[k]):
                raise ConfigError(f"errors.{k} = {v!r} is not accepted: a number in [0, {MAX_ERRORS[k]:g}]")
        if not isinstance(errors.randomise, bool):
            raise ConfigError(f"errors.randomise = {errors.randomise!r} is not accepted: True or False")
        self.view = errors.view
        self.sizes = jnp.asarray([errors[k] for k in ERROR_SIZES], jnp.float32)
        # a static choice: with no error at all the observation is RegraspEnv's own, bit for bit
        self.noisy = any(errors[k] > 0.0 for k in ERROR_SIZES)

    # ---- Playground's MjxEnv interface ---------------------------------------------------------
    @property
    def config(self) -> config_dict.ConfigDict:
        return self._config

    @property
    def env_config(self) -> EnvConfig:
        return self.env.config

    @property
    def observation_size(self) -> int:
        return self.env.observation_size

    @property
    def action_size(self) -> int:
        return self.env.action_size

    @property
    def mj_model(self) -> mujoco.MjModel:
        return self.env.scene.model

    @property
    def mjx_model(self):
        return self.env.scene.mjx_model

    @property
    def unwrapped(self) -> RegistryEnv:
        return self

    def reset(self, rng: jax.Array) -> State:
        """A new problem from the task's distributions and this episode's error draws."""
        k_env, k_errors = jax.random.split(rng)
        return self._start(self.env.reset(k_env), k_errors)

    def reset_from(self, episode: Episode, rng: jax.Array) -> State:
        """Starts from a given problem (a test-set row), its errors drawn by ``rng``."""
        return self._start(self.env.reset_from(episode), rng)

    def step(self, state: State, action: jax.Array) -> State:
        """Carries out ``action`` (the policy's motion in its view) and observes the result."""
        inner = BraxState(state.data, state.obs, state.reward, state.done, state.metrics, state.info)
        a = self.env.checked_action(action)
        if self.view != "exact":  # the motion asked for in the view, as the arm carries it out
            _, seen_ee = self.view_of(state.data, state.info)
            ee = jnp.concatenate([state.data.ee_pos, state.data.ee_quat])[None]
            a = robot_errors.executed(None, ee, seen_ee[None], a[None], self.env.max_dp, self.env.max_drot)[0]
        inner = self.env.move(inner, a[:3] * self.env.max_dp, a[3:] * self.env.max_drot)
        return self._state(inner)

    # ---- the errors ----------------------------------------------------------------------------
    def _start(self, inner: BraxState, key: jax.Array) -> State:
        k_sizes, k_noise, k_arms = jax.random.split(key, 3)
        scale = jax.random.uniform(k_sizes, (len(ERROR_SIZES),)) if self._config.errors.randomise else 1.0
        sizes = self.sizes * scale
        errors = dict(zip(ERROR_SIZES, sizes))
        start = jnp.concatenate([inner.pipeline_state.ee_pos, inner.pipeline_state.ee_quat])[None]
        arms = robot_errors.draw_arms(k_arms, start, errors["calibration_mm"], errors["calibration_deg"], 0.0)
        info = {**inner.info, "errors": errors, "noise_key": k_noise, "arms": arms}
        return self._state(inner.replace(info=info))

    def view_of(self, es: EpisodeState, info: dict) -> tuple[jax.Array, jax.Array]:
        """The needle and the regrasping tool ``[7]`` each as the policy sees them now (its frame
        at step ``es.t`` a pure function of the state, so observing twice sees the same)."""
        needle = jnp.concatenate([es.needle_pos, es.needle_quat])[None]
        ee = jnp.concatenate([es.ee_pos, es.ee_quat])[None]
        if not self.noisy:
            return needle[0], ee[0]
        errors = info["errors"]
        k_bias, k_frames = jax.random.split(info["noise_key"])
        k_frame = jax.random.fold_in(k_frames, es.t)
        seen = estimates.needle_estimate(k_bias, k_frame, needle, errors["needle_sigma_mm"], errors["needle_bias_mm"])
        seen_ee = ee
        if self.view == "camera":
            k_tools = jax.random.fold_in(k_frame, 7)
            seen, seen_ee = estimates.camera_view(k_tools, seen, ee, errors["tool_noise_mm"][None])
        elif self.view == "kinematic":
            seen, seen_ee = robot_errors.kinematic_view(info["arms"], seen, ee, None)
        return seen[0], seen_ee[0]

    def _state(self, inner: BraxState) -> State:
        es = inner.pipeline_state
        obs = inner.obs
        if self.noisy:
            seen, seen_ee = self.view_of(es, inner.info)
            seen_es = estimates.seen_from(es, seen).replace(ee_pos=seen_ee[:3], ee_quat=seen_ee[3:])
            obs = self.env.observe(seen_es)
        return State(es, obs, inner.reward, inner.done, inner.metrics, inner.info)

    # ---- pictures ------------------------------------------------------------------------------
    def render(self, trajectory: list[State], height: int = 240, width: int = 320, camera: str | None = None):
        """RGB frames ``[height, width, 3]`` of unbatched states (Playground's ``render``): the true
        needle, both tools and the goal as a ghost (:class:`~regrasp_mjx.workflows.render.SceneRenderer`)."""
        frames = []
        with SceneRenderer(self.env.scene, width, height, camera=camera) as renderer:
            for state in trajectory:
                es = jax.device_get(state.data)
                pose = lambda p, q: jnp.concatenate([p, q])  # noqa: E731
                frames.append(
                    renderer.image(
                        pose(es.needle_pos, es.needle_quat),
                        pose(es.ee_pos, es.ee_quat),
                        pose(es.goal_pos, es.goal_quat),
                    )
                )
        return frames
