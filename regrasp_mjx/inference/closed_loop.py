"""Closed-loop regrasping under needle-pose noise: re-plan every step from the latest estimate.

A plan made once from a noisy needle pose is executed open loop against the true needle, so its
error is never corrected. A lab re-estimates the needle every camera frame and the policy is fast
enough to act on every one: each step the policy acts on the latest estimate (or on the fused
estimate of all frames so far: the needle does not move relative to the grasping tool, so the frames
can simply be averaged), and the regrasp stops when the estimate says the goal is reached. In
simulation (:func:`make_executor`) success and collision are judged on the true needle.
:func:`execute` and :func:`closed_loop_step` are the host entry points (``Policy.execute``,
``Policy.closed_loop_step``).

The needle-estimate noise model and the noisy observation are in :mod:`regrasp_mjx.envs.estimates`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core import geometry
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs import estimates
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.envs.rollout import rollout
from regrasp_mjx.envs.shield import shield_rows
from regrasp_mjx.inference.planner import mean_action, members_apply
from regrasp_mjx.inference.plans import auto_engine, checked_goals
from regrasp_mjx.inference.queries import PoseError, TaskSpec, batch_poses, check_poses
from regrasp_mjx.robot.robot_errors import (
    RobotErrors,
    average,
    check_observe,
    draw_arms,
    executed,
    first_readings,
    kinematic_pose,
    kinematic_view,
    propagate,
    readings,
)
from regrasp_mjx.world.sampling import Episode

FRAMES = ("one", "each", "fused")  # open loop; closed loop on each frame; closed loop on the fused frames


def _with_needle(state, needle: jax.Array, ee: jax.Array | None = None):
    """``state`` as a view shows it: the needle (and the regrasping tool) there."""
    es = estimates.seen_from(state.pipeline_state, needle)
    if ee is not None:
        es = es.replace(ee_pos=ee[:, :3], ee_quat=ee[:, 3:])
    return state.replace(pipeline_state=es)


def _at_goal(env: RegraspEnv, state, needle: jax.Array, tol=None) -> jax.Array:
    """Whether the end-effector is at the goal grasp on ``needle`` (eqs. 8, 9 on that needle), within
    ``tol`` (metres, radians; Python floats or traced; default the task's own, :func:`tolerances`)."""
    tol = tolerances(env.config, 1.0) if tol is None else tol
    es = state.pipeline_state
    current = geometry.relative((es.ee_pos, es.ee_quat), (needle[:, :3], needle[:, 3:]))
    dist, angle = geometry.pose_error(current, (es.goal_needle_pos, es.goal_needle_quat))
    return (dist <= tol[0]) & (angle <= tol[1])


def tolerances(config, scale: float) -> tuple[float, float]:
    """An ``EnvConfig``'s success tolerances scaled by ``scale`` (metres, radians; Python floats). The
    executor takes their float32 as an argument, one program for every stop tolerance: the same
    comparisons as the float32 constants they were."""
    return scale * config.success_pos_mm * 1e-3, scale * math.radians(config.success_rot_deg)


def choose_action(env: RegraspEnv, apply: Callable, weights, state, t: jax.Array, shield: bool, live=None):
    """The policy's action on ``state`` (whose needle is the estimate) and, with ``shield``, for
    the ``live`` rows (default all) whose action the estimate says collides, the first of the
    shield's alternatives that it says is free (:func:`regrasp_mjx.envs.shield.shield_rows`)."""
    step = jax.vmap(env.step)
    a = mean_action(apply(weights, state.obs))
    if not shield:
        return a
    nxt = step(state, a)
    need = nxt.metrics["collision"] > 0
    need = need if live is None else need & live
    return shield_rows(step, lambda sub: apply(weights, sub.obs), state, t, a, nxt, need)[0]


# the executor's keys beyond the needle frames' (0 .. horizon + 1 + warmup): the robot's errors, the tool frames
ARMS_KEY, TOOLS_KEY = 1 << 20, (1 << 20) + 1


def make_executor(
    env: RegraspEnv,
    apply: Callable,
    shield: bool,
    frames: str = "fused",
    shield_env: RegraspEnv | None = None,
    warmup: int = 1,
    observe: str = "camera",
    joints: bool = False,
):
    """``run(weights, needle, start, goal, key, sigma_mm, bias_mm, radii=None, robot=None, stop=None) -> dict``
    (jitted): regrasping in simulation for ``[B, 7]`` true needle, start and goal poses (e_g frame;
    ``radii`` ``[B, 2]``: each needle's radius and wire radius in metres, for a task that varies
    needles; ``robot``: the :class:`~regrasp_mjx.robot.robot_errors.RobotErrors` numbers
    ``(calibration_mm, calibration_deg, joint_offset, tool_noise_mm)``, default none; ``stop``: the
    view's stop tolerances (metres, radians; :func:`tolerances`), default the task's own: an
    argument, so one program serves every stop tolerance).

    Each step the policy acts on a view of the needle and of its tool (``observe``, one of
    :data:`~regrasp_mjx.robot.robot_errors.OBSERVE`): with ``frames="one"`` the first frame held for the
    whole episode (a plan made once, executed open loop), ``"each"`` that step's frame,
    ``"fused"`` the mean of the frames so far (``warmup`` of them before the first step; a tool
    the camera sees is moved between frames by its kinematics). Its action is carried out
    relative to the arm's current pose (:func:`regrasp_mjx.robot.robot_errors.executed`; ``joints``:
    through the arm's inverse kinematics with its joint offsets, needed where ``joint_offset > 0``).
    ``shield_env`` (default ``env``) is what the shield checks its alternatives with, in the view:
    one with a clearance margin keeps that much away from the estimate. Returns per row:
    ``success`` (stopped at the goal of the true needle, no collision), ``collision`` (on the true
    needle), ``time_out`` (no stop within the horizon), ``stopped`` (the view said the goal was
    reached), ``steps`` and ``poses`` ``[B, horizon + 1, 7]`` (true). The loop is
    :func:`regrasp_mjx.envs.rollout.rollout` with a stopping rule (the view's) and the policy acting on
    the view."""
    if frames not in FRAMES:
        raise ConfigError(f"frames={frames!r} is not accepted: one of {FRAMES}")
    check_observe(observe)
    horizon = env.config.horizon
    shield_env = env if shield_env is None else shield_env
    fused, camera = frames == "fused", observe == "camera"
    seen0 = warmup - 1 if fused else 0

    def move(state, a):  # an executed action: unclipped (the view's error may turn it off the axes)
        return env.move(state, a[:3] * env.max_dp, a[3:] * env.max_drot)

    def run(weights, needle, start, goal, key, sigma_mm, bias_mm, radii=None, robot=None, stop=None):
        b = needle.shape[0]
        stop_tol = tolerances(env.config, 1.0) if stop is None else stop
        calibration_mm, calibration_deg, joint_offset, tool_noise_mm = (0.0,) * 4 if robot is None else robot
        episode = Episode.from_poses(needle, start, goal, radii)
        state = jax.vmap(env.reset_from)(episode)
        ee0 = jnp.concatenate([state.pipeline_state.ee_pos, state.pipeline_state.ee_quat], -1)
        arms = draw_arms(jax.random.fold_in(key, ARMS_KEY), ee0, calibration_mm, calibration_deg, joint_offset)
        k_tools = jax.random.fold_in(key, TOOLS_KEY)
        biased = estimates.episode_bias(jax.random.fold_in(key, horizon + 1), needle, bias_mm)
        q0 = first_readings(arms) if joints else None
        exact_tools = jnp.broadcast_to(jnp.asarray(tool_noise_mm) == 0.0, (b,))

        def view(frame, ee, q):
            """Frame ``frame``'s needle and tool as the policy sees them, and where the tool's
            kinematics say it is (what a camera-seen tool's mean is moved by between frames)."""
            estimate = estimates.frame_estimate(jax.random.fold_in(key, frame), biased, sigma_mm)
            if camera:
                seen = estimates.camera_view(jax.random.fold_in(k_tools, frame), estimate, ee, tool_noise_mm)
            else:
                seen = kinematic_view(arms, estimate, ee, q)
            return seen, (ee if q is None else kinematic_pose(q))

        total, tool = jnp.zeros((b, 7)), ee0
        if fused:  # frames before the first step (the tool holds still): keys beyond the horizon's
            for i in range(warmup - 1):
                (frame_needle, frame_tool), _ = view(horizon + 2 + i, ee0, q0)
                total = estimates.fuse(total, frame_needle, biased)
                tool = frame_tool if i == 0 else average(tool, jnp.float32(i), frame_tool)
        # the rule's per-row data rides in state.info: the fused frames, the view acted on, where the
        # kinematics put the tool, its readings, and which rows act at this step (the shield works
        # on those alone)
        info = {
            **state.info,
            "needle_total": total,
            "needle_seen": needle,
            "ee_seen": tool,
            "kinematics": ee0 if q0 is None else kinematic_pose(q0),
            "acting": jnp.ones(b, bool),
        }
        if joints:
            info["readings"] = q0
        state = state.replace(info=info)

        def stop(state, t, live):
            """This step's frame: stop where the view says the goal is reached (a success
            where the true poses agree)."""
            es, info = state.pipeline_state, state.info
            ee = jnp.concatenate([es.ee_pos, es.ee_quat], -1)
            q = readings(arms, ee, info["readings"]) if joints else None
            (frame_needle, frame_tool), kin = view(0 if frames == "one" else t, ee, q)
            total = estimates.fuse(info["needle_total"], frame_needle, biased)
            seen = estimates.mean_pose(total, (t + 1 + seen0).astype(jnp.float32)) if fused else frame_needle
            tool = frame_tool
            if camera and frames != "each":  # the view so far, moved as the kinematics say
                moved = propagate(info["ee_seen"], info["kinematics"], kin)
                count = (t + seen0).astype(jnp.float32)
                if fused:
                    tool = jnp.where(count > 0, average(moved, count, frame_tool), frame_tool)
                else:  # one frame, then the plan's own motion
                    tool = jnp.where(t > 0, moved, frame_tool)
                tool = jnp.where(exact_tools[:, None], frame_tool, tool)  # a camera that sees the tool exactly
            stopping = _at_goal(env, _with_needle(state, seen, tool), seen, stop_tol)
            acting = live & ~stopping & (t < horizon)
            info = {**info, "needle_total": total, "needle_seen": seen, "ee_seen": tool, "kinematics": kin}
            info["acting"] = acting
            if joints:
                info["readings"] = q
            return state.replace(info=info), stopping, _at_goal(env, state, needle)

        def act(state, t):
            """The policy (and the shield) on the view, carried out on the true tool."""
            info = state.info
            seen = _with_needle(state, info["needle_seen"], info["ee_seen"])
            seen = seen.replace(obs=jax.vmap(env.observe)(seen.pipeline_state))
            a = choose_action(shield_env, apply, weights, seen, t, shield, info["acting"])
            es = state.pipeline_state
            ee = jnp.concatenate([es.ee_pos, es.ee_quat], -1)
            a = jnp.clip(a, -1.0, 1.0)
            done = executed(arms, ee, info["ee_seen"], a, env.max_dp, env.max_drot, info.get("readings"))
            # a view equal to the truth moves the tool by the action exactly (as without errors)
            return jnp.where(jnp.all(info["ee_seen"] == ee, -1, keepdims=True), a, done)

        def pose(state, a, nxt):
            return jnp.concatenate([nxt.pipeline_state.ee_pos, nxt.pipeline_state.ee_quat], axis=1)

        out = rollout(env, act, state, max_steps=horizon, stop=stop, trace=pose, step=jax.vmap(move))
        # [B, horizon + 1, 7]: the start, the pose after each step, the last one held after the end
        trace = jnp.concatenate([start[None].astype(out.trace.dtype), out.trace], axis=0)
        held = jnp.minimum(jnp.arange(horizon + 1)[:, None], out.steps[None, :])
        poses = jnp.take_along_axis(trace, held[..., None], axis=0).transpose(1, 0, 2)
        return {
            "start_valid": out.start_valid,
            "success": out.success,
            "collision": out.collision,
            "time_out": out.time_out,
            "stopped": out.stopped,
            "steps": out.steps.astype(jnp.int32),
            "poses": poses,
        }

    return jax.jit(run)


def make_stepper(env: RegraspEnv, apply: Callable, shield: bool, stop_scale: float = 1.0):
    """``step(weights, needle, ee, goal, t, radii=None) -> (action, next_ee, at_goal)`` (jitted,
    ``[B, 7]`` poses in e_g; ``radii`` as :func:`make_executor`'s): one closed-loop step from the
    current estimates. ``at_goal`` (within
    ``stop_scale`` of the success tolerances on the estimate) rows should stop (their action is zero
    and ``next_ee`` is ``ee``)."""

    def one(weights, needle, ee, goal, t, radii=None):
        episode = Episode.from_poses(needle, ee, goal, radii)
        state = jax.vmap(env.reset_from)(episode)
        done = _at_goal(env, state, needle, tolerances(env.config, stop_scale))
        a = jnp.where(done[:, None], 0.0, choose_action(env, apply, weights, state, t, shield, ~done))
        es = jax.vmap(env.step)(state, a).pipeline_state
        nxt = jnp.where(done[:, None], ee, jnp.concatenate([es.ee_pos, es.ee_quat], axis=1))
        return jnp.clip(a, -1.0, 1.0), nxt, done

    return jax.jit(one)


# ---- the host entry points (Policy.closed_loop_step, Policy.execute) ------------------------------


def _estimate_inputs(policy: Any, needle: Any, ee_name: str, ee: Any, goal: Any, spec: TaskSpec):
    """Checked ``[B, 7]`` needle, end-effector and goal poses (the goal grasp on ``needle`` by
    default), each needle's radii ``[B, 2]`` (m) and whether one query was given."""
    (needle, ee), single = batch_poses(needle=needle, **{ee_name: ee})
    grasp, radii = policy.task_ranges.resolve(len(needle), spec)
    return needle, ee, checked_goals(needle, goal, grasp, radii), radii, single


def _program(
    policy, kind, shield, frames="fused", clearance_mm=0.0, stop=1.0, warmup=1, observe="camera", joints=False
):
    """The jitted executor (``kind="execute"``) or stepper of a setting, built once per network shape."""

    def build():
        env = RegraspEnv(policy.env_config)
        guard = RegraspEnv(dataclasses.replace(policy.env_config, clearance_mm=clearance_mm)) if clearance_mm else env
        apply = members_apply(policy.hidden)
        if kind == "execute":
            return make_executor(env, apply, shield, frames, guard, warmup, observe, joints)
        return make_stepper(guard, apply, shield, stop)

    return policy.program((kind, shield, frames, clearance_mm, stop, warmup, observe, joints), build)


def closed_loop_step(
    policy: Any,
    needle: Any,
    ee: Any,
    goal: Any = None,
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
    ``ee``). ``t`` is the step index (it seeds the shield's alternatives, as in a plan); the
    shield checks the alternatives against the estimated needle, keeping ``clearance_mm`` from it
    (room for the estimate's error). ``at_goal`` holds within ``stop_tolerance`` of the success
    tolerances (None: the policy's own, ``Policy.closed_loop_defaults``), as in :func:`execute`.
    ``task``: the goal grasp and needle keywords (:class:`~regrasp_mjx.inference.queries.TaskSpec`). One
    query on the CPU (no ``clearance_mm``, ``t`` within the horizon) takes the lean numba step
    (:meth:`regrasp_mjx.inference.lean_planner.LeanPlanner.step`), anything else the jitted JAX program."""
    stop_tolerance = policy.closed_loop_defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
    spec = TaskSpec.of(task)
    (needle, ee), single = batch_poses(needle=needle, ee=ee)
    if single and not clearance_mm and 0 <= t < policy.env_config.horizon and auto_engine(1) == "lean":
        # one query on the CPU: the lean numba step, its default goal made by the compiled code (the
        # JAX program below stays the reference)
        lean = policy.lean(shield)
        grasp, radii = policy.task_ranges.resolve(1, spec)
        goal = lean.goal(needle[0], grasp[0], radii[0, 0]) if goal is None else check_poses("goal", goal)
        if goal.shape != (7,):
            raise PoseError(f"goal {goal.shape} and needle (7,) poses differ in batch size")
        at_goal, nxt, a = lean.step(needle[0], ee[0], goal, radii[0], int(t), float(stop_tolerance))
        return a, nxt, np.bool_(at_goal)
    needle, ee, goal, radii, single = _estimate_inputs(policy, needle, "ee", ee, goal, spec)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    step = _program(policy, "step", shield, clearance_mm=float(clearance_mm), stop=float(stop_tolerance))
    a, nxt, done = jax.device_get(step(f32(needle), f32(ee), f32(goal), np.int32(t), f32(radii)))
    a, nxt, done = np.asarray(a, np.float64), np.asarray(nxt, np.float64), np.asarray(done)
    return (a[0], nxt[0], done[0]) if single else (a, nxt, done)


def execute(
    policy: Any,
    needle: Any,
    start: Any,
    goal: Any = None,
    noise: NeedleNoise | None = None,
    frames: str = "fused",
    shield: bool = True,
    seed: int = 0,
    clearance_mm: float = 0.0,
    stop_tolerance: float | None = None,
    warmup_frames: int | None = None,
    robot: RobotErrors | None = None,
    observe: str = "camera",
    **task: Any,
) -> dict[str, np.ndarray]:
    """Simulates regrasping under needle-pose noise on true needle, start and goal poses ``[B, 7]``
    (e_g frame): each step the policy acts on an estimate of the needle (``noise``, a
    :class:`~regrasp_mjx.envs.estimates.NeedleNoise`; default none) and stops when the estimate says the
    goal is reached; success and collisions are judged on the true needle. ``frames``: ``"fused"``
    (the mean of the frames so far, the default), ``"each"`` (that step's frame alone) or ``"one"``
    (the first frame for the whole episode: a plan made once, executed open loop).
    ``clearance_mm``: the shield keeps this clearance from the estimated needle (room for the
    estimate's error); ``stop_tolerance``: stop when the estimate is within this fraction of the
    success tolerances (below 1: room for the estimate's error at the goal); ``warmup_frames``:
    with ``"fused"``, frames fused before the first step (the tool holds still meanwhile). Their
    defaults (None) are the policy's own (``Policy.closed_loop_defaults``: chosen for it on
    validation problems of their own seed by experiments/closed_loop_select.py; 10 frames and 0.7
    where its file names none); ``frames="one", stop_tolerance=1`` with no noise reproduces a plan
    exactly. ``robot``: the robot's errors (a :class:`~regrasp_mjx.robot.robot_errors.RobotErrors`:
    camera-to-base calibration, joint offsets, tool tracking noise; default none) and
    ``observe``: how the policy sees its tools through them, ``"camera"`` (tools and needle from
    the camera, the default) or ``"kinematic"`` (tools from the joint readings).
    ``task``: the goal grasp and needle keywords (a general policy's ranges). Returns
    numpy arrays per row: ``success``, ``collision``, ``time_out``, ``stopped``, ``steps``,
    ``start_valid``, ``poses``."""
    noise = NeedleNoise() if noise is None else noise
    robot = RobotErrors() if robot is None else robot
    if not isinstance(noise, NeedleNoise):
        raise ConfigError(f"noise={noise!r} is not accepted: a NeedleNoise")
    if not isinstance(robot, RobotErrors):
        raise ConfigError(f"robot={robot!r} is not accepted: a RobotErrors")
    check_observe(observe)
    defaults = policy.closed_loop_defaults
    stop_tolerance = defaults["stop_tolerance"] if stop_tolerance is None else stop_tolerance
    warmup_frames = defaults["warmup_frames"] if warmup_frames is None else warmup_frames
    if frames not in FRAMES:
        raise ConfigError(f"frames={frames!r} is not accepted: one of {FRAMES}")
    if not (isinstance(warmup_frames, int) and warmup_frames >= 1):
        raise ConfigError(f"warmup_frames={warmup_frames!r} is not accepted: an integer >= 1")
    if not (math.isfinite(stop_tolerance) and 0.0 < stop_tolerance <= 1.0):
        raise ConfigError(f"stop_tolerance={stop_tolerance!r} is not accepted: a fraction in (0, 1]")
    needle, start, goal, radii, _ = _estimate_inputs(policy, needle, "start", start, goal, TaskSpec.of(task))
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    warmup = int(warmup_frames) if frames == "fused" else 1
    joints = robot.joint_offset > 0
    # the stop tolerance is an argument (1.0 in the key)
    run = _program(policy, "execute", shield, frames, float(clearance_mm), 1.0, warmup, observe, joints)
    key = jax.random.PRNGKey(seed)
    errors = tuple(
        f32(v) for v in (robot.calibration_mm, robot.calibration_deg, robot.joint_offset, robot.tool_noise_mm)
    )
    stop = tuple(f32(x) for x in tolerances(policy.env_config, float(stop_tolerance)))
    out = run(
        f32(needle), f32(start), f32(goal), key, f32(noise.sigma_mm), f32(noise.bias_mm), f32(radii), errors, stop
    )
    return {k: np.asarray(v) for k, v in jax.device_get(out).items()}
