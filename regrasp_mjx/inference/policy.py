"""Loaded policies: :class:`Policy` (the network, what it was trained for, its planners) and
:func:`load_policy`.

What a policy does with poses lives in plain functions: planning in :mod:`regrasp_mjx.inference.plans`, the
closed loop in :mod:`regrasp_mjx.inference.closed_loop`, the checks of a query in :mod:`regrasp_mjx.inference.queries`.
The file format and the shipped policies are :mod:`regrasp_mjx.inference.policy_file` (what callers import of
it re-exported here), the compiled programs :func:`regrasp_mjx.inference.planner.program`.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.config_text import env_config_from_dict
from regrasp_mjx.core.config_text import replace as config_replace
from regrasp_mjx.inference import camera_loop, closed_loop_host, planner, plans
from regrasp_mjx.inference.planner import mean_action, members_apply
from regrasp_mjx.inference.plans import Plan
from regrasp_mjx.inference.policy_file import (
    DEFAULT_POLICY,
    PolicyError,
    closed_loop_settings,
    obs_size,
    read_policy,
    save_policy,
    shipped_policies,
)
from regrasp_mjx.inference.queries import START_WARN_MM, PoseError, TaskRanges, check_poses

# what callers import through this module (the re-exported names live in policy_file, queries, planner)
__all__ = [
    "DEFAULT_POLICY",
    "START_WARN_MM",
    "Policy",
    "PolicyError",
    "PoseError",
    "check_poses",
    "ensemble_policies",
    "load_policy",
    "mean_action",
    "save_policy",
    "shipped_policies",
]


@dataclasses.dataclass(frozen=True)
class Policy:
    """A loaded policy: the network (``act(obs[..., 21]) -> action[..., 6]``), what it was trained
    for, its compiled programs, and planning and the closed loop (plain functions in
    :mod:`regrasp_mjx.inference.plans` and :mod:`regrasp_mjx.inference.closed_loop`). The task keywords every
    entry point takes are :class:`~regrasp_mjx.inference.queries.TaskSpec`'s (``goal_alpha_rad``, ``goal_depth_mm``,
    ``goal_theta_rad``, ``goal_phi_rad``, ``needle_radius_mm``, ``wire_radius_mm``; None: its own)."""

    contract: dict[str, Any]
    actor_params: Any  # leaves with a leading member axis
    normalizer: Any

    def __post_init__(self) -> None:
        apply = members_apply(self.hidden)
        # the weights as one pytree of device arrays: the planners take them as an argument, so
        # policies of one network shape share their compiled programs
        pick = lambda tree, i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
        norm = self.normalizer
        weights = jax.device_put(
            tuple((pick(self.actor_params, i), norm.mean[i], norm.std[i]) for i in range(self.members))
        )
        object.__setattr__(self, "_weights", weights)
        object.__setattr__(self, "_apply", apply)
        object.__setattr__(self, "_member_actions", functools.partial(apply, weights))
        object.__setattr__(self, "_actor", lambda obs: mean_action(apply(weights, obs)))
        object.__setattr__(self, "_act", jax.jit(self._actor))
        object.__setattr__(self, "_programs", {})  # what planner.program() and planner.lean() built

    def __repr__(self) -> str:
        ens = f"{self.members} x " if self.members > 1 else ""
        task = "general" if self.general else "paper"
        return f"Policy({ens}{'x'.join(map(str, self.hidden))}, {self.obs_size} inputs, {task} task)"

    # ---- the network -------------------------------------------------------------------------
    @property
    def hidden(self) -> tuple[int, ...]:
        return tuple(self.contract["network"]["hidden"])

    @property
    def members(self) -> int:
        return int(self.contract["network"].get("ensemble", 1))

    @functools.cached_property
    def obs_size(self) -> int:
        """Inputs of the network: 21 (the paper's task), 37 (a general task)."""
        return obs_size(self.env_config)

    def act(self, obs: Any) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.shape[-1:] != (self.obs_size,):
            raise ValueError(f"observation has shape {obs.shape}; accepted: (..., {self.obs_size})")
        if not np.all(np.isfinite(obs)):
            raise ValueError("observation has NaN or inf; accepted: finite values")
        return np.asarray(self._act(jnp.asarray(obs)))

    def actor_fn(self) -> Callable:
        """The pure function ``obs[..., 21] -> action[..., 6]``, parameters closed over (to jit or export)."""
        return self._actor

    def network(self) -> tuple[Callable, Any]:
        """``(apply, weights)``: the pure ``apply(weights, obs[..., 21]) -> [each member's action]``
        and the weights to pass it (device arrays). Jit with the weights as an argument, not closed
        over, and policies of one network shape share the compiled program (and the persistent
        compilation cache: a recipe's students of three teachers compile theirs once)."""
        return self._apply, self._weights

    def members_fn(self) -> Callable:
        """``obs[..., 21] -> [action[..., 6] of each member]``; :meth:`actor_fn` is their mean."""
        return self._member_actions

    # ---- what it was trained for ------------------------------------------------------------
    @functools.cached_property
    def env_config(self):
        """The environment it was trained in (built from the contract once: policies are frozen)."""
        return dataclasses.replace(env_config_from_dict(self.contract["env"]), check_actions=False)

    def with_env(self, **changes: Any) -> Policy:
        """The same network planning in a changed environment, e.g. ``with_env(clearance_mm=0.1)``
        (a pose then collides closer than 0.1 mm to the needle or the other tool, and the shield
        keeps that margin); names as :func:`regrasp_mjx.core.config_text.replace` takes them (dotted for
        nested fields). Raises :class:`~regrasp_mjx.core.config.ConfigError` for a bad field or value."""
        env = config_replace(env_config_from_dict(self.contract["env"]), **changes)
        return dataclasses.replace(self, contract={**copy.deepcopy(self.contract), "env": dataclasses.asdict(env)})

    @functools.cached_property
    def general(self) -> bool:
        """Trained on a general task (ranges of the goal grasp or the needle; 37 inputs)."""
        return self.env_config.task.general

    @functools.cached_property
    def task_ranges(self) -> TaskRanges:
        """What it was trained for (``resolve``: a :class:`TaskSpec` checked, as goal grasps and needles)."""
        return TaskRanges.of(self.env_config)

    def trained_ranges(self) -> dict[str, tuple[float, float]]:
        """``(low, high)`` of each task keyword (one value twice where it was fixed)."""
        return self.task_ranges.as_dict()

    @property
    def closed_loop_defaults(self) -> dict[str, Any]:
        """Its closed loop's ``stop_tolerance`` and ``warmup_frames``
        (:func:`regrasp_mjx.inference.policy_file.closed_loop_settings`)."""
        return closed_loop_settings(self.contract)

    # ---- its programs -----------------------------------------------------------------------
    def program(self, setting: tuple, build: Callable[[], Callable] | None = None) -> Callable:
        """The jitted program of ``setting``, weights bound: :func:`regrasp_mjx.inference.planner.program`."""
        return planner.program(self, setting, build)

    def lean(self, shield: bool):
        """The numba-compiled one-query planner: :func:`regrasp_mjx.inference.planner.lean`."""
        return planner.lean(self, shield)

    # ---- what it does with poses (the functions say how) -------------------------------------
    def plan(self, needle: Any, start: Any, goal: Any = None, **options: Any) -> Plan:
        """Plans from poses in the grasping end-effector frame e_g (7-vectors, or batches ``[B, 7]``);
        options ``check_grasp``, ``shield``, ``engine`` and the task keywords:
        :func:`regrasp_mjx.inference.plans.plan`."""
        return plans.plan(self, needle, start, goal, **options)

    def plan_from_camera(self, grasping_ee: Any, regrasping_ee: Any, needle: Any, **options: Any) -> Plan:
        """Plans from three camera-frame poses, as on a real dVRK (options ``check_grasp``,
        ``shield``, ``psm``, ``respect_limits``, ``timed`` and the task keywords):
        :func:`regrasp_mjx.inference.plans.plan_from_camera`."""
        return plans.plan_from_camera(self, grasping_ee, regrasping_ee, needle, **options)

    def closed_loop_step(self, needle: Any, ee: Any, goal: Any = None, **options: Any):
        """One closed-loop step from the current estimates: ``(action, next_ee, at_goal)``
        (:func:`regrasp_mjx.inference.closed_loop_host.closed_loop_step`)."""
        return closed_loop_host.closed_loop_step(self, needle, ee, goal, **options)

    def camera_loop(self, **options: Any):
        """A closed loop driven by camera frames of both tools and the needle, in which a
        camera-to-base calibration error cancels (options ``goal_in_needle``, ``warmup_frames``,
        ``stop_tolerance``, ``shield``, ``look_frames``, ``camera``, ``jaw_sigmas`` and the task
        keywords; jaws that open on the way carried): :class:`regrasp_mjx.inference.camera_loop.CameraLoop`."""
        return camera_loop.CameraLoop(self, **options)

    def execute(self, needle: Any, start: Any, goal: Any = None, noise: Any = None, **options: Any) -> dict:
        """Simulates regrasping under needle-pose noise on true poses ``[B, 7]``
        (:func:`regrasp_mjx.inference.closed_loop_host.execute`)."""
        return closed_loop_host.execute(self, needle, start, goal, noise, **options)


def ensemble_policies(
    paths: list[str | os.PathLike],
    out_dir: str | os.PathLike,
    extra: dict | None = None,
    weights_dtype: str = "float32",
) -> Path:
    """Stacks single policies of one network and environment into one mean-action ensemble."""
    policies = [load_policy(p) for p in paths]
    first = policies[0].contract
    for p, pol in zip(paths, policies):
        if pol.contract["network"]["hidden"] != first["network"]["hidden"] or pol.contract["env"] != first["env"]:
            raise PolicyError(f"{p}: another network or environment than {paths[0]}; an ensemble needs one")
    stack = lambda *xs: jnp.concatenate(xs)  # noqa: E731  (each member already has its axis)
    actor = jax.tree.map(stack, *[p.actor_params for p in policies])
    norm = types.SimpleNamespace(
        mean=stack(*[p.normalizer.mean for p in policies]), std=stack(*[p.normalizer.std for p in policies])
    )
    return save_policy(
        out_dir,
        actor,
        norm,
        tuple(first["network"]["hidden"]),
        env_config_from_dict(first["env"]),
        extra={"ensemble_of": {"members": [str(p) for p in paths], **(extra or {})}},
        ensemble=sum(p.members for p in policies),
        weights_dtype=weights_dtype,
    )


def load_policy(path: str | os.PathLike | None = None) -> Policy:
    """Reads a policy folder (or its ``policy.json``/``policy.npz``) and checks it against its
    contract; with no path, the policy shipped in the package; a bare name that is no existing
    path, one of :func:`shipped_policies` (``load_policy("ensemble3")``)."""
    return Policy(*read_policy(path))
