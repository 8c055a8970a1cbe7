"""Loaded policies: ``Policy.act``, ``Policy.plan`` and ``Policy.plan_from_camera``, pose checks, ensembles.

Planning rolls the deterministic policy out in the same environment it was trained in (kinematics
and exact collision checks, on whatever device JAX uses) until success, collision or the horizon,
shielded by default, and returns the trajectory (the program: :mod:`regrasp_mjx.planner`). The file
format and the shipped policies are :mod:`regrasp_mjx.policy_file`, re-exported here.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import os
import types
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx import closed_loop, dvrk, geometry, host
from regrasp_mjx.config import ConfigError, env_config_from_dict
from regrasp_mjx.config import replace as config_replace
from regrasp_mjx.env import RegraspEnv
from regrasp_mjx.estimates import NeedleNoise
from regrasp_mjx.geometry import QUAT_NORM_TOLERANCE, unit_quaternions
from regrasp_mjx.grasps import GraspLibrary
from regrasp_mjx.planner import PLANNERS, PlanArrays, goal_pose_in_needle, make_planner, mean_action, members_apply
from regrasp_mjx.policy_file import (
    ACTION_LAYOUT,
    DEFAULT_POLICY,
    OBS_LAYOUT,
    POLICY_FORMAT,
    POLICY_VERSION,
    SHIPPED,
    WEIGHT_DTYPES,
    PolicyError,
    obs_size,
    read_policy,
    save_policy,
    shipped_policies,
)

__all__ = [
    "ACTION_LAYOUT",
    "DEFAULT_POLICY",
    "OBS_LAYOUT",
    "POLICY_FORMAT",
    "POLICY_VERSION",
    "QUAT_NORM_TOLERANCE",
    "SHIPPED",
    "WEIGHT_DTYPES",
    "Plan",
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


class PoseError(ValueError):
    """A pose that is not a finite 7-vector ``[x, y, z, qw, qx, qy, qz]`` with a unit quaternion."""


ENGINES = ("auto", "jax", "lean")  # Policy.plan's planning programs


def auto_engine(queries: int) -> str:
    """What ``Policy.plan(engine="auto")`` runs ``queries`` queries with: the lean numba rollout for
    one query when JAX runs on the CPU, the jitted JAX program otherwise."""
    return "lean" if queries == 1 and jax.default_backend() == "cpu" else "jax"


OOD_WARN_DISTANCE = 4.0  # nearest-grasp distance (mm + deg/5) beyond which a plan warns (fresh draws: p99 2.7)


def check_poses(name: str, poses: Any) -> np.ndarray:
    """``poses[..., 7]`` as float64 with unit quaternions, or a :class:`PoseError` saying why not."""
    arr = np.asarray(poses, np.float64)
    if arr.shape == (7,):  # one good pose in scalar arithmetic: numpy's calls would cost more than a lean plan
        x = arr.tolist()
        norm = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5] + x[6] * x[6])
        if all(map(math.isfinite, x)) and abs(norm - 1.0) <= QUAT_NORM_TOLERANCE:
            return np.array(x[:3] + [v / norm for v in x[3:]])
    if arr.ndim == 0 or arr.shape[-1] != 7:
        raise PoseError(f"{name} has shape {arr.shape}; accepted: (..., 7) = [x, y, z, qw, qx, qy, qz] in metres")
    if not np.all(np.isfinite(arr)):
        raise PoseError(f"{name} has NaN or inf; accepted: finite values")
    return np.concatenate([arr[..., :3], unit_quaternions(name, arr[..., 3:], PoseError)], axis=-1)


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
    members = sum(p.members for p in policies)
    return save_policy(
        out_dir,
        actor,
        norm,
        tuple(first["network"]["hidden"]),
        env_config_from_dict(first["env"]),
        extra={"ensemble_of": {"members": [str(p) for p in paths], **(extra or {})}},
        ensemble=members,
        weights_dtype=weights_dtype,
    )


def _first(x):
    return None if x is None else x[0]


@dataclasses.dataclass(frozen=True)
class Plan:
    """A planned regrasp, numpy. Batched plans have a leading query axis on every field.

    Attributes:
      success, collision, time_out: how the rollout ended (one is true; ``start_valid`` false means
        the start pose already collides and nothing was planned).
      steps: actions taken (the trajectory's valid length is ``steps + 1`` poses).
      path_length_mm: sum of the translation steps.
      poses: regrasping end-effector poses ``[x, y, z, qw, qx, qy, qz]`` in the grasping
        end-effector frame e_g, float32, the start first; ``T + 1`` rows, T the most steps any
        plan of the call took (a single query: its own ``steps``), rows after a plan's ``steps``
        repeat its last pose.
      actions: ``T`` rows in [-1, 1], float32; rows from a plan's ``steps`` on are zero.
      poses_camera: the same poses in the camera frame (only from :meth:`Policy.plan_from_camera`),
        the same shape as ``poses`` (padded with the last pose): the trajectory itself is
        ``trajectory("camera")``, ``steps + 1`` rows.
      nearest_grasp_distance: distance of the needle pose to the nearest of the valid-grasp library
        (``regrasp_mjx.grasps``; mm + deg / 5), when checked.
      joints: with ``plan_from_camera(..., psm=...)``, the regrasping PSM's
        :class:`~regrasp_mjx.dvrk.JointTrajectory` of the valid poses (a list of them for a batch).
      grasping_joints: likewise the grasping PSM's :class:`~regrasp_mjx.dvrk.IKResult` at its pose.
    """

    success: np.ndarray
    collision: np.ndarray
    time_out: np.ndarray
    start_valid: np.ndarray
    steps: np.ndarray
    path_length_mm: np.ndarray
    poses: np.ndarray
    actions: np.ndarray
    poses_camera: np.ndarray | None = None
    nearest_grasp_distance: np.ndarray | None = None
    joints: Any = None
    grasping_joints: Any = None

    def __repr__(self) -> str:
        ok = np.atleast_1d(self.success)
        if ok.size == 1 and np.ndim(self.success) == 0:
            return f"Plan(success={bool(self.success)}, steps={int(self.steps)}, path_length_mm={float(self.path_length_mm):.2f})"
        return f"Plan({ok.size} queries: success {ok.mean():.3f}, collision {np.mean(self.collision):.3f})"

    def trajectory(self, frame: str = "eg") -> np.ndarray:
        """The valid poses of a single plan (``steps + 1`` rows), in ``eg`` or ``camera`` frame."""
        poses = self.poses if frame == "eg" else self.poses_camera
        if poses is None or poses.ndim != 2:
            raise ValueError(f"trajectory() takes one plan with {frame} poses; index a batch first")
        return poses[: int(self.steps) + 1]


START_WARN_MM = 60.0  # a start this far from its needle is no regrasping problem we trained on

# the closed loop's settings where a policy file names none (chosen for `student_v1` on validation)
CLOSED_LOOP_STOP, CLOSED_LOOP_WARMUP = 0.7, 10


@dataclasses.dataclass(frozen=True)
class Policy:
    """A loaded policy: ``act(obs[..., 21]) -> action[..., 6]`` and ``plan`` (jitted, deterministic)."""

    contract: dict[str, Any]
    actor_params: Any  # leaves with a leading member axis
    normalizer: Any

    def __post_init__(self) -> None:
        apply = members_apply(tuple(self.contract["network"]["hidden"]))
        # the weights as one pytree of device arrays: the planners take them as an argument, so
        # policies of one network shape share their compiled programs
        pick = lambda tree, i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
        norm = self.normalizer
        weights = jax.device_put(
            tuple((pick(self.actor_params, i), norm.mean[i], norm.std[i]) for i in range(self.members))
        )

        def member_actions(obs):
            return apply(weights, obs)

        def act(obs):
            return mean_action(member_actions(obs))

        object.__setattr__(self, "_weights", weights)
        object.__setattr__(self, "_member_actions", member_actions)
        object.__setattr__(self, "_actor", act)
        object.__setattr__(self, "_act", jax.jit(act))
        object.__setattr__(self, "_planners", {})  # (camera, shield) -> the shared program, weights bound
        object.__setattr__(self, "_one_task", None)  # _task_inputs of one query with no task arguments

    def __repr__(self) -> str:
        net = "x".join(str(h) for h in self.contract["network"]["hidden"])
        ens = f"{self.members} x " if self.members > 1 else ""
        return f"Policy({ens}{net}, {self.obs_size} inputs, {'general' if self.general else 'paper'} task)"

    @property
    def members(self) -> int:
        return int(self.contract["network"].get("ensemble", 1))

    def member(self, i: int) -> Policy:
        """Network ``i`` of an ensemble as a policy of its own."""
        if not 0 <= i < self.members:
            raise ValueError(f"member {i} is not accepted: this policy has {self.members} (0..{self.members - 1})")
        contract = copy.deepcopy(self.contract)
        contract["network"]["ensemble"] = 1
        norm = types.SimpleNamespace(mean=self.normalizer.mean[i : i + 1], std=self.normalizer.std[i : i + 1])
        params = jax.tree.map(lambda x: x[i : i + 1], self.actor_params)
        return dataclasses.replace(self, contract=contract, actor_params=params, normalizer=norm)

    @property
    def env_config(self):
        return dataclasses.replace(env_config_from_dict(self.contract["env"]), check_actions=False)

    def with_env(self, **changes: Any) -> Policy:
        """The same network planning in a changed environment, e.g. ``with_env(clearance_mm=0.1)``
        (a pose then collides closer than 0.1 mm to the needle or the other tool, and the shield
        keeps that margin); names as :func:`regrasp_mjx.config.replace` takes them (dotted for
        nested fields). Raises :class:`~regrasp_mjx.config.ConfigError` for a bad field or value."""
        env = config_replace(env_config_from_dict(self.contract["env"]), **changes)
        contract = copy.deepcopy(self.contract)
        contract["env"] = dataclasses.asdict(env)
        return dataclasses.replace(self, contract=contract)

    @property
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

    def actor_fn(self):
        """The pure function ``obs[..., 21] -> action[..., 6]`` with the parameters closed over (for
        jitting into other programs or exporting)."""
        return self._actor

    def members_fn(self):
        """The pure function ``obs[..., 21] -> [action[..., 6] of each member]`` (one entry for one
        network); :meth:`actor_fn` is their mean."""
        return self._member_actions

    # ---- planning ---------------------------------------------------------------------------
    def _planner(self, camera: bool, shield: bool = True):
        """One jitted program: poses in, rollout until every query ended, trajectory out.

        With ``shield`` a step whose policy action would collide takes instead the first
        collision-free one of a fixed list of alternatives (see :func:`shield_candidates`),
        checked with the same collision model the plan is judged by; a plan then only collides
        when none of them is free. The alternatives are only computed at steps where some query's
        policy action collides."""
        if (camera, shield) not in self._planners:  # looked up once per policy, not per plan
            key = (tuple(self.contract["network"]["hidden"]), self.members, json.dumps(self.contract["env"]))
            key += (camera, shield)
            if key not in PLANNERS:
                PLANNERS[key] = make_planner(self.env_config, tuple(self.contract["network"]["hidden"]), camera, shield)
            self._planners[(camera, shield)] = functools.partial(PLANNERS[key], self._weights)
        return self._planners[(camera, shield)]

    def _finish(self, out: PlanArrays, single: bool, nearest) -> Plan:
        o = out.outcome
        pick = _first if single else (lambda x: x)  # one query: its row of every field  # noqa: E731
        # both planners return the trajectories cut after the longest plan, float32: no copy here
        return Plan(
            success=pick(o.success),
            collision=pick(o.collision),
            time_out=pick(o.time_out),
            start_valid=pick(o.start_valid),
            steps=pick(o.steps.astype(np.int64)),
            path_length_mm=pick(o.path_length_mm),
            poses=pick(out.poses),
            actions=pick(out.actions),
            poses_camera=pick(out.poses_camera),
            nearest_grasp_distance=pick(nearest),
        )

    # ---- closed loop ----------------------------------------------------------------------
    def _closed_loop(
        self,
        kind: str,
        shield: bool,
        frames: str = "fused",
        clearance_mm: float = 0.0,
        stop: float = 1.0,
        warmup: int = 1,
    ):
        setting = (kind, shield, frames, clearance_mm, stop, warmup)
        if setting not in self._planners:
            key = (tuple(self.contract["network"]["hidden"]), self.members, json.dumps(self.contract["env"]))
            key += setting
            if key not in PLANNERS:
                env = RegraspEnv(self.env_config)
                guard = (
                    RegraspEnv(dataclasses.replace(self.env_config, clearance_mm=clearance_mm)) if clearance_mm else env
                )
                apply = members_apply(tuple(self.contract["network"]["hidden"]))
                PLANNERS[key] = (
                    closed_loop.make_executor(env, apply, shield, frames, guard, stop, warmup)
                    if kind == "execute"
                    else closed_loop.make_stepper(guard, apply, shield, stop)
                )
            self._planners[setting] = functools.partial(PLANNERS[key], self._weights)
        return self._planners[setting]

    def _estimate_inputs(self, needle: Any, ee_name: str, ee: Any, goal: Any, task: dict[str, Any]):
        """Checked ``[B, 7]`` needle, end-effector and goal poses (the goal grasp on ``needle`` by
        default), each needle's radii ``[B, 2]`` (m) and whether one query was given, for the
        closed-loop entry points; ``task``: :meth:`plan`'s goal-grasp and needle keywords."""
        needle, ee = check_poses("needle", needle), check_poses(ee_name, ee)
        single = needle.ndim == 1
        needle, ee = np.atleast_2d(needle), np.atleast_2d(ee)
        if needle.shape != ee.shape:
            raise PoseError(f"needle {needle.shape} and {ee_name} {ee.shape} poses differ in batch size")
        grasp, radii = self._task_inputs(len(needle), **task)
        if goal is None:
            goal = self._default_goal(needle, grasp, radii)
        goal = np.atleast_2d(check_poses("goal", goal))
        if goal.shape != needle.shape:
            raise PoseError(f"goal {goal.shape} and needle {needle.shape} poses differ in batch size")
        return needle, ee, goal, radii, single

    def closed_loop_step(
        self,
        needle: Any,
        ee: Any,
        goal: Any = None,
        goal_depth_mm: Any = None,
        t: int = 0,
        shield: bool = True,
        clearance_mm: float = 0.0,
        stop_tolerance: float | None = None,
        **task: Any,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One closed-loop step from the current estimates (e_g frame, 7-vectors or ``[B, 7]``): the
        latest (or fused) needle estimate and the regrasping end-effector's current pose. Returns
        ``(action, next_ee, at_goal)``: the action, the pose to command next, and whether the
        estimate says the goal is already reached (then stop: the action is zero, ``next_ee`` is
        ``ee``). ``t`` is the step index (it seeds the shield's alternatives, as in :meth:`plan`);
        the shield checks the alternatives against the estimated needle, keeping
        ``clearance_mm`` from it (room for the estimate's error). ``at_goal`` holds within
        ``stop_tolerance`` of the success tolerances (None: the policy's own,
        :attr:`closed_loop_defaults`), as in :meth:`execute`. ``task``: the goal grasp and needle
        keywords of :meth:`plan` (``goal_alpha_rad``, ``needle_radius_mm``, ...)."""
        stop_tolerance = self.closed_loop_defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
        needle, ee, goal, radii, single = self._estimate_inputs(
            needle, "ee", ee, goal, {"goal_depth_mm": goal_depth_mm, **task}
        )
        f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
        step = self._closed_loop("step", shield, clearance_mm=float(clearance_mm), stop=float(stop_tolerance))
        a, nxt, done = jax.device_get(step(f32(needle), f32(ee), f32(goal), np.int32(t), f32(radii)))
        a, nxt, done = np.asarray(a, np.float64), np.asarray(nxt, np.float64), np.asarray(done)
        return (a[0], nxt[0], done[0]) if single else (a, nxt, done)

    def execute(
        self,
        needle: Any,
        start: Any,
        goal: Any = None,
        noise: Any = None,
        frames: str = "fused",
        shield: bool = True,
        seed: int = 0,
        goal_depth_mm: Any = None,
        clearance_mm: float = 0.0,
        stop_tolerance: float | None = None,
        warmup_frames: int | None = None,
        **task: Any,
    ) -> dict[str, np.ndarray]:
        """Simulates regrasping under needle-pose noise (:mod:`regrasp_mjx.closed_loop`) on true
        needle, start and goal poses ``[B, 7]`` (e_g frame): each step the policy acts on an
        estimate of the needle (``noise``, a :class:`~regrasp_mjx.estimates.NeedleNoise`; default
        none) and stops when the estimate says the goal is reached; success and collisions are
        judged on the true needle. ``frames``: ``"fused"`` (the mean of the frames so far, the
        default), ``"each"`` (that step's frame alone) or ``"one"`` (the first frame for the whole
        episode: a plan made once, executed open loop). ``clearance_mm``: the shield keeps this
        clearance from the estimated needle (room for the estimate's error); ``stop_tolerance``:
        stop when the estimate is within this fraction of the success tolerances (below 1: room
        for the estimate's error at the goal); ``warmup_frames``: with ``"fused"``, frames fused
        before the first step (the tool holds still meanwhile). Their defaults (None) are the
        policy's own (:attr:`closed_loop_defaults`: chosen for it on validation problems of their
        own seed by experiments/closed_loop_select.py; 10 frames and 0.7 where its file names
        none); ``frames="one", stop_tolerance=1`` with no noise
        reproduces :meth:`plan` exactly. ``task``: the goal grasp and needle keywords of
        :meth:`plan` (a general policy's ranges). Returns numpy arrays per row: ``success``,
        ``collision``, ``time_out``, ``stopped``, ``steps``, ``start_valid``, ``poses``."""

        noise = NeedleNoise() if noise is None else noise
        defaults = self.closed_loop_defaults
        stop_tolerance = defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
        warmup_frames = defaults["warmup_frames"] if warmup_frames is None else warmup_frames
        if frames not in closed_loop.FRAMES:
            raise ConfigError(f"frames={frames!r} is not accepted: one of {closed_loop.FRAMES}")
        if not (isinstance(warmup_frames, int) and warmup_frames >= 1):
            raise ConfigError(f"warmup_frames={warmup_frames!r} is not accepted: an integer >= 1")
        if not (math.isfinite(stop_tolerance) and 0.0 < stop_tolerance <= 1.0):
            raise ConfigError(f"stop_tolerance={stop_tolerance!r} is not accepted: a fraction in (0, 1]")
        needle, start, goal, radii, _ = self._estimate_inputs(
            needle, "start", start, goal, {"goal_depth_mm": goal_depth_mm, **task}
        )
        f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
        warmup = int(warmup_frames) if frames == "fused" else 1
        run = self._closed_loop("execute", shield, frames, float(clearance_mm), float(stop_tolerance), warmup)
        key = jax.random.PRNGKey(seed)
        out = run(f32(needle), f32(start), f32(goal), key, f32(noise.sigma_mm), f32(noise.bias_mm), f32(radii))
        return {k: np.asarray(v) for k, v in jax.device_get(out).items()}

    @property
    def closed_loop_defaults(self) -> dict[str, Any]:
        """The closed loop's settings for this policy (:meth:`execute`, :meth:`closed_loop_step`):
        ``stop_tolerance`` and ``warmup_frames`` from its file's ``closed_loop`` entry (chosen for
        it on validation problems), else 0.7 and 10 (chosen so for an earlier default)."""
        given = self.contract.get("closed_loop") or {}
        return {
            "stop_tolerance": float(given.get("stop_tolerance", CLOSED_LOOP_STOP)),
            "warmup_frames": int(given.get("warmup_frames", CLOSED_LOOP_WARMUP)),
        }

    @property
    def general(self) -> bool:
        """Trained on a general task (ranges of the goal grasp or the needle; 37 inputs)."""
        return self.env_config.task.general

    def trained_ranges(self) -> dict[str, tuple[float, float]]:
        """What this policy was trained for: ``(low, high)`` of each goal-grasp coordinate and of the
        needle (one value twice where it was fixed), the names :meth:`plan` takes."""
        env = self.env_config
        task = env.task
        return {
            "goal_depth_mm": tuple(float(v) for v in task.goal_depth_mm),
            "goal_alpha_rad": task.span("goal_alpha_range_rad", task.goal_alpha_rad),
            "goal_theta_rad": task.span("goal_theta_range_rad", task.goal_theta_rad),
            "goal_phi_rad": task.span("goal_phi_range_rad", task.goal_phi_rad),
            "needle_radius_mm": task.span("needle_radius_range_mm", env.scene.needle_radius_mm),
            "wire_radius_mm": task.span("wire_radius_range_mm", env.scene.wire_radius_mm),
        }

    _TASK_INPUTS = (
        "goal_alpha_rad",
        "goal_depth_mm",
        "goal_theta_rad",
        "goal_phi_rad",
        "needle_radius_mm",
        "wire_radius_mm",
    )

    @functools.cached_property
    def _task_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """Defaults, lows and highs of :data:`_TASK_INPUTS` (looked up once), and whether theta*
        spans a full turn."""
        env, ranges = self.env_config, self.trained_ranges()
        task = env.task
        defaults = {
            "goal_depth_mm": sum(task.goal_depth_mm) / 2,
            "goal_alpha_rad": task.goal_alpha_rad,
            "goal_theta_rad": task.goal_theta_rad,
            "goal_phi_rad": task.goal_phi_rad,
            "needle_radius_mm": env.scene.needle_radius_mm,
            "wire_radius_mm": env.scene.wire_radius_mm,
        }
        lo = np.array([ranges[k][0] for k in self._TASK_INPUTS])
        hi = np.array([ranges[k][1] for k in self._TASK_INPUTS])
        full_turn = hi[2] - lo[2] >= 2 * np.pi - 1e-6
        return np.array([defaults[k] for k in self._TASK_INPUTS]), lo, hi, full_turn

    def _task_inputs(self, n: int, **given: Any) -> tuple[np.ndarray, np.ndarray]:
        """Each query's goal grasp ``[n, 4]`` = ``(alpha*, d* [m], theta*, phi*)`` and needle ``[n, 2]``
        = ``(R, wire radius)`` [m] from ``plan``'s keyword arguments (scalars or ``[n]``; None: the
        task's goal grasp, the middle of the depth range, the scene's needle), each checked against
        the trained range: a :class:`PoseError` names the range (a specialist's is one value)."""
        plain = n == 1 and all(v is None for v in given.values())
        if plain and self._one_task is not None:  # one query of the task's own goal and needle: as last time
            return self._one_task
        defaults, lo, hi, full_turn = self._task_table
        values = np.empty((n, len(self._TASK_INPUTS)))
        values[:] = defaults
        for col, name in enumerate(self._TASK_INPUTS):
            if given.get(name) is not None:
                values[:, col] = np.asarray(given[name], np.float64)
        if full_turn:  # any azimuth: wrapped into the trained turn
            values[:, 2] = lo[2] + np.mod(values[:, 2] - lo[2], 2 * np.pi)
        tol = 1e-6 * np.maximum(1.0, np.abs(hi))
        bad = ~np.isfinite(values) | (values < lo - tol) | (values > hi + tol)
        if bad.any():
            row, col = (int(v) for v in np.argwhere(bad)[0])
            name = self._TASK_INPUTS[col]
            trained = f"{lo[col]:.6g}" if lo[col] == hi[col] else f"[{lo[col]:.6g}, {hi[col]:.6g}]"
            hint = "" if self.general else " (a specialist: load_policy('general') plans any goal grasp and needle)"
            where = f" (query {row})" if n > 1 else ""
            raise PoseError(
                f"{name}={values[row, col]:.6g}{where} is not accepted: this policy was trained for {name} = "
                f"{trained}{hint}"
            )
        grasp = values[:, :4].copy()
        grasp[:, 1] *= 1e-3
        out = grasp, values[:, 4:] * 1e-3
        if plain:
            for x in out:
                x.flags.writeable = False
            object.__setattr__(self, "_one_task", out)
        return out

    def plan(
        self,
        needle: Any,
        start: Any,
        goal: Any = None,
        goal_depth_mm: Any = None,
        check_grasp: bool = True,
        shield: bool = True,
        *,
        goal_alpha_rad: Any = None,
        goal_theta_rad: Any = None,
        goal_phi_rad: Any = None,
        needle_radius_mm: Any = None,
        wire_radius_mm: Any = None,
        engine: str = "auto",
    ) -> Plan:
        """Plans from poses in the grasping end-effector frame e_g (7-vectors, or batches ``[B, 7]``).

        ``goal`` defaults to the goal grasp ``(goal_alpha_rad, goal_depth_mm, goal_theta_rad,
        goal_phi_rad)`` on this needle (each None: the task's goal grasp, the middle of the trained
        depth range). ``needle_radius_mm`` and ``wire_radius_mm`` name the needle (None: the
        scene's, the paper's 5.4 and 0.25 mm). Each may be a scalar or one value per query; each
        must lie in what the policy was trained for (:meth:`trained_ranges`): a specialist takes
        its one goal grasp and needle, a general policy their ranges. ``shield`` replaces a policy
        action that would collide by the first collision-free alternative
        (:func:`shield_candidates`); ``shield=False`` rolls the policy out as trained. Raises
        :class:`PoseError` on bad input; warns when the needle pose of a paper-task policy is far
        from every valid grasp of the library.

        ``engine``: ``"jax"`` runs the jitted program (:mod:`regrasp_mjx.planner`; any batch, any
        device); ``"lean"`` the same rollout compiled with numba for one query on the CPU
        (:mod:`regrasp_mjx.lean_planner`, several times faster there; it gives the JAX path's
        verdicts, and its actions to float32 rounding); ``"auto"`` (default) takes the lean one
        for a single query when JAX runs on the CPU.
        """
        if engine not in ENGINES:
            raise ValueError(f"engine={engine!r} is not accepted; accepted: {', '.join(map(repr, ENGINES))}")
        needle = check_poses("needle", needle)
        start = check_poses("start", start)
        single = needle.ndim == 1
        needle, start = np.atleast_2d(needle), np.atleast_2d(start)
        if needle.shape != start.shape:
            raise PoseError(f"needle {needle.shape} and start {start.shape} poses differ in batch size")
        grasp, radii = self._task_inputs(
            len(needle),
            goal_depth_mm=goal_depth_mm,
            goal_alpha_rad=goal_alpha_rad,
            goal_theta_rad=goal_theta_rad,
            goal_phi_rad=goal_phi_rad,
            needle_radius_mm=needle_radius_mm,
            wire_radius_mm=wire_radius_mm,
        )
        if engine == "auto":
            engine = auto_engine(len(needle))
        if engine == "lean" and len(needle) != 1:
            raise ValueError(f"engine='lean' plans one query at a time; got {len(needle)}: use engine='jax'")
        if goal is None:
            if engine == "lean":  # no eager JAX ops on the one-query path: milliseconds against microseconds
                goal = self._lean_planner(shield).goal(needle[0], grasp[0], radii[0, 0])
            else:
                goal = self._default_goal(needle, grasp, radii)
        goal = np.atleast_2d(check_poses("goal", goal))
        if goal.shape != needle.shape:
            raise PoseError(f"goal {goal.shape} and needle {needle.shape} poses differ in batch size")
        nearest = self._check_grasp(needle) if check_grasp and not self.general else None
        _check_start_distance(needle, start)
        if engine == "lean":
            out = self._lean_planner(shield)(needle[0], start[0], goal[0], radii[0])
        else:
            f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731  (numpy in: the fastest dispatch)
            out = self._planner(False, shield)(f32(needle), f32(start), f32(goal), f32(radii))
        return self._finish(out, single, nearest)

    def _lean_planner(self, shield: bool):
        """The numba-compiled one-query rollout (:mod:`regrasp_mjx.lean_planner`), built once."""
        if ("lean", shield) not in self._planners:
            # imported here: numba's import and first compilation are paid only where it is used
            from regrasp_mjx.lean_planner import LeanPlanner

            self._planners[("lean", shield)] = LeanPlanner(self.env_config, self._weights, shield)
        return self._planners[("lean", shield)]

    def plan_from_camera(
        self,
        grasping_ee: Any,
        regrasping_ee: Any,
        needle: Any,
        goal_depth_mm: Any = None,
        check_grasp: bool = True,
        shield: bool = True,
        psm: dict | None = None,
        respect_limits: bool = True,
        *,
        goal_alpha_rad: Any = None,
        goal_theta_rad: Any = None,
        goal_phi_rad: Any = None,
        needle_radius_mm: Any = None,
        wire_radius_mm: Any = None,
    ) -> Plan:
        """Plans from three camera-frame poses (7-vectors or ``[B, 7]``), as on a real dVRK
        (SPEC "Deployment"); the plan's poses come in the e_g frame and the camera frame.
        ``shield``, the goal grasp and the needle as in :meth:`plan`.

        ``psm``: ``{"regrasping_base": pose, "grasping_base": pose}`` (camera-frame 7-vectors or 4x4
        of each PSM's base, i.e. remote-centre-of-motion, frame; ``grasping_base`` optional). The
        plan then also holds the regrasping arm's joint trajectory with a per-pose joint-limit
        verdict (``Plan.joints``) and the grasping arm's joints at its pose (``Plan.grasping_joints``)
        from :mod:`regrasp_mjx.dvrk`; out-of-limit poses are reported, not changed. With
        ``respect_limits`` (and the shield) the shield also replaces an action whose end pose would
        leave the regrasping arm's joint limits, as it replaces a colliding one."""
        c_eg = check_poses("grasping_ee", grasping_ee)
        c_er = check_poses("regrasping_ee", regrasping_ee)
        c_n = check_poses("needle", needle)
        single = c_eg.ndim == 1
        c_eg, c_er, c_n = (np.atleast_2d(x) for x in (c_eg, c_er, c_n))
        if not (c_eg.shape == c_er.shape == c_n.shape):
            raise PoseError(f"camera poses differ in batch size: {c_eg.shape}, {c_er.shape}, {c_n.shape}")
        grasp, radii = self._task_inputs(
            len(c_eg),
            goal_depth_mm=goal_depth_mm,
            goal_alpha_rad=goal_alpha_rad,
            goal_theta_rad=goal_theta_rad,
            goal_phi_rad=goal_phi_rad,
            needle_radius_mm=needle_radius_mm,
            wire_radius_mm=wire_radius_mm,
        )
        nearest = None
        if check_grasp and not self.general:
            rel = [host.relative(e[:3], e[3:], n[:3], n[3:]) for e, n in zip(c_eg, c_n)]
            rel_p, rel_q = np.stack([r[0] for r in rel]), np.stack([r[1] for r in rel])
            nearest = self._check_grasp(np.concatenate([rel_p, rel_q], axis=1))
        f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731  (numpy in: the fastest dispatch)
        base_inv = None
        if psm is not None:
            unknown = set(psm) - {"regrasping_base", "grasping_base"}
            if "regrasping_base" not in psm or unknown:
                raise PoseError(
                    f"psm={sorted(psm)} is not accepted: a dict with 'regrasping_base' (and 'grasping_base')"
                )
            if respect_limits and shield:  # the base frame's inverse in e_g, per query
                base = np.linalg.inv(dvrk.as_matrix(psm["regrasping_base"]))
                base_inv = f32([base @ dvrk.pose_matrix(e) for e in c_eg])
        out = self._planner(True, shield)(f32(c_eg), f32(c_er), f32(c_n), f32(grasp), f32(radii), base_inv)
        plan = self._finish(out, single, nearest)
        return plan if psm is None else _with_joints(plan, psm, c_eg, single)

    def _default_goal(self, needle: np.ndarray, grasp: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """The goal end-effector poses ``[n, 7]`` (e_g) of goal grasps ``[n, 4]`` on needles."""
        goal = geometry.compose(
            (jnp.asarray(needle[:, :3]), jnp.asarray(needle[:, 3:])),
            goal_pose_in_needle(jnp.asarray(grasp), jnp.asarray(radii[:, 0])),
        )
        return np.concatenate([np.asarray(goal[0]), np.asarray(goal[1])], axis=1)

    def _check_grasp(self, needle: np.ndarray) -> np.ndarray:

        dist = GraspLibrary.default().nearest(needle)[1]
        far = dist > OOD_WARN_DISTANCE
        if np.any(far):
            warnings.warn(
                f"needle pose {int(np.argmax(far))} is {float(dist[far][0]):.2f} (mm + deg/5) from the nearest "
                f"valid grasp of the library (beyond {OOD_WARN_DISTANCE}): far from anything trained on; "
                "project it with regrasp_mjx.grasps.GraspLibrary.project or check the pose estimate",
                stacklevel=3,
            )
        return dist


def far_starts(needle: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Which starts ``[n, 7]`` lie implausibly far from their needles ``[n, 7]`` (beyond
    :data:`START_WARN_MM`; every trained start lies within about 30 mm): a bool ``[n]``."""
    return start_distance_mm(np.asarray(needle), np.asarray(start)) > START_WARN_MM


def start_distance_mm(needle: np.ndarray, start: np.ndarray) -> np.ndarray:
    """``[n]`` distances of starts ``[n, 7]`` from their needles ``[n, 7]``, mm."""
    if len(start) == 1:  # one query: plain floats (numpy's calls would cost as much as a lean plan)
        return np.array([math.dist(start[0, :3].tolist(), needle[0, :3].tolist()) * 1e3])
    return np.linalg.norm(start[:, :3] - needle[:, :3], axis=1) * 1e3


def _check_start_distance(needle: np.ndarray, start: np.ndarray) -> None:
    """Warns about starts implausibly far from their needle (e.g. given in millimetres, not metres)."""
    dist = start_distance_mm(needle, start)
    far = dist > START_WARN_MM
    if far.any():
        warnings.warn(
            f"start {int(np.argmax(far))} is {float(dist[far][0]):.4g} mm from its needle (beyond {START_WARN_MM:g} mm, "
            "where no start was trained): poses are in metres; check the units and the frame",
            stacklevel=3,
        )


def _with_joints(plan: Plan, psm: dict, c_eg: np.ndarray, single: bool) -> Plan:

    steps = np.atleast_1d(plan.steps)
    cam = plan.poses_camera[None] if single else plan.poses_camera
    joints = [dvrk.joint_trajectory(psm["regrasping_base"], cam[i][: steps[i] + 1]) for i in range(len(cam))]
    grasping = None
    if psm.get("grasping_base") is not None:
        base_inv = np.linalg.inv(dvrk.as_matrix(psm["grasping_base"]))
        grasping = [dvrk.inverse_kinematics(base_inv @ dvrk.pose_matrix(e)) for e in c_eg]
    if single:
        joints, grasping = joints[0], None if grasping is None else grasping[0]
    return dataclasses.replace(plan, joints=joints, grasping_joints=grasping)


def load_policy(path: str | os.PathLike | None = None) -> Policy:
    """Reads a policy folder (or its ``policy.json``/``policy.npz``) and checks it against its
    contract; with no path, the policy shipped in the package; a bare name that is no existing
    path, one of :func:`shipped_policies` (``load_policy("ensemble3")``)."""
    return Policy(*read_policy(path))
