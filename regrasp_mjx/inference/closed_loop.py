"""Closed-loop regrasping under needle-pose noise: re-plan every step from the latest estimate.

A plan made once from a noisy needle pose is executed open loop against the true needle, so its
error is never corrected. A lab re-estimates the needle every camera frame and the policy is fast
enough to act on every one: each step the policy acts on the latest estimate (or on the fused
estimate of all frames so far: the needle does not move relative to the grasping tool, so the frames
can simply be averaged), and the regrasp stops when the estimate says the goal is reached. In
simulation (:func:`make_executor`) success and collision are judged on the true needle.
:func:`~regrasp_mjx.inference.closed_loop_host.execute` and
:func:`~regrasp_mjx.inference.closed_loop_host.closed_loop_step` are the host entry points
(``Policy.execute``, ``Policy.closed_loop_step``).

The needle-estimate noise model and the noisy observation are in :mod:`regrasp_mjx.envs.estimates`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

from regrasp_mjx.core import geometry
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.envs import camera_errors, estimates
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.rollout import rollout
from regrasp_mjx.envs.shield import shield_rows
from regrasp_mjx.inference import jaw_opening
from regrasp_mjx.inference.planner import mean_action
from regrasp_mjx.robot.robot_errors import (
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
from regrasp_mjx.world import jaw
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


# the executor's keys beyond the needle frames' (0 .. horizon + 1 + warmup): the robot's errors, the
# tool frames, the drifts, the looked frames (LOOK_KEY + t * look + i: below ARMS_KEY for MAX_LOOK)
ARMS_KEY, TOOLS_KEY, DRIFT_KEY, LOOK_KEY = 1 << 20, (1 << 20) + 1, (1 << 20) + 2, 1 << 16
MAX_LOOK = 300  # frames one look may take (10 s at 30 fps)
NEAR = 2.0  # a view within this many stop tolerances of the goal is about to make its last moves


def make_executor(
    env: RegraspEnv,
    apply: Callable,
    shield: bool,
    frames: str = "fused",
    shield_env: RegraspEnv | None = None,
    warmup: int = 1,
    observe: str = "camera",
    joints: bool = False,
    look: int = 0,
    jaw_sigmas: float = 1.0,
):
    """``run(weights, needle, start, goal, key, camera, radii=None, robot=None, stop=None) -> dict``
    (jitted): regrasping in simulation for ``[B, 7]`` true needle, start and goal poses (e_g frame;
    ``camera``: the camera's errors, :meth:`~regrasp_mjx.envs.camera_errors.CameraErrors.numbers`;
    ``radii`` ``[B, 2]``: each needle's radius and wire radius in metres, for a task that varies
    needles; ``robot``: the :class:`~regrasp_mjx.robot.robot_errors.RobotErrors` numbers
    ``(calibration_mm, calibration_deg, joint_offset)``, default none; ``stop``: the view's stop
    tolerances (metres, radians; :func:`tolerances`), default the task's own: an argument, so one
    program serves every stop tolerance and every camera).

    Each step the policy acts on a view of the needle and of its tool (``observe``, one of
    :data:`~regrasp_mjx.robot.robot_errors.OBSERVE`): with ``frames="one"`` the first frame held for the
    whole episode (a plan made once, executed open loop), ``"each"`` that step's frame,
    ``"fused"`` the mean of the frames so far (``warmup`` of them before the first step; a tool
    the camera sees is moved between frames by its kinematics). With ``look`` > 0 (fused only), a
    row looks before its last moves (the first time its view comes within :data:`NEAR` times the
    stop tolerances of the goal) and before it declares the goal reached (the first time its view
    says so): it holds still and fuses frames while its estimate is too uncertain to stop on
    (twice the fused estimate's standard deviation, from the camera's known error sizes, exceeds
    the room between the stop and the success tolerance), at most ``look`` frames, then decides
    again. Its action is carried out
    relative to the arm's current pose (:func:`regrasp_mjx.robot.robot_errors.executed`; ``joints``:
    through the arm's inverse kinematics with its joint offsets, needed where ``joint_offset > 0``).
    ``shield_env`` (default ``env``) is what the shield checks its alternatives with, in the view:
    one with a clearance margin keeps that much away from the estimate. Where the policy's jaws open
    on the way (``EnvConfig.jaw_open_deg``), the loop opens them before the first step whose view
    leaves the opening sweep the environment's margin plus ``jaw_sigmas`` standard deviations of the
    view's known error at the jaws (:func:`regrasp_mjx.envs.camera_errors.view_sd_mm`); the truth judges the sweep (a collision
    where it is not proved clear). Returns per row:
    ``success`` (stopped at the goal of the true needle, no collision), ``collision`` (on the true
    needle), ``time_out`` (no stop within the horizon), ``stopped`` (the view said the goal was
    reached), ``steps``, ``frames`` (every frame fused: warm-up, one per step, looked),
    ``looked`` (the frames spent looking), ``jaw_deg`` (the jaws' last opening), ``opened_at`` (the
    step they opened before, -1 if never), ``opening_collision`` (that opening's sweep not proved clear
    on the true poses: a part of ``collision``), ``start_seen`` ``[B, 14]`` (the needle and the tool as the
    view showed them when the first move was decided) and ``poses`` ``[B, horizon + 1, 7]`` (true). The loop is
    :func:`regrasp_mjx.envs.rollout.rollout` with a stopping rule (the view's) and the policy acting on
    the view."""
    if frames not in FRAMES:
        raise ConfigError(f"frames={frames!r} is not accepted: one of {FRAMES}")
    check_observe(observe)
    if not (isinstance(look, int) and 0 <= look <= MAX_LOOK) or (look and frames != "fused"):
        raise ConfigError(f"look={look!r} is not accepted: frames in [0, {MAX_LOOK}], and only with fused frames")
    horizon = env.config.horizon
    shield_env = env if shield_env is None else shield_env
    fused, camera = frames == "fused", observe == "camera"
    axis = jnp.asarray(camera_errors.depth_axis(), jnp.float32)
    reach = jaw.jaw_reach(env.scene)

    def move(state, a):  # an executed action: unclipped (the view's error may turn it off the axes)
        opening = {"open_to": a[6]} if env.opens else {}  # the loop's decision rides as a seventh number
        return env.move(state, a[:3] * env.max_dp, a[3:6] * env.max_drot, **opening)

    def run(weights, needle, start, goal, key, errors, radii=None, robot=None, stop=None):
        b = needle.shape[0]
        success_tol = tolerances(env.config, 1.0)
        stop_tol = success_tol if stop is None else stop
        calibration_mm, calibration_deg, joint_offset = (0.0,) * 3 if robot is None else robot
        pn, pt, depth = errors[:5], errors[5:10], (errors[10], axis)  # the needle's, the tools', the depth
        episode = Episode.from_poses(needle, start, goal, radii)
        state = jax.vmap(env.reset_from)(episode)
        ee0 = jnp.concatenate([state.pipeline_state.ee_pos, state.pipeline_state.ee_quat], -1)
        arms = draw_arms(jax.random.fold_in(key, ARMS_KEY), ee0, calibration_mm, calibration_deg, joint_offset)
        k_tools, k_drift = jax.random.fold_in(key, TOOLS_KEY), jax.random.fold_in(key, DRIFT_KEY)
        biased = camera_errors.biased(jax.random.fold_in(key, horizon + 1), needle, pn[0], pn[4], depth)
        tool_bias = jax.random.split(jax.random.fold_in(k_tools, TOOLS_KEY), 2)
        q0 = first_readings(arms) if joints else None
        exact_tools = jnp.broadcast_to(camera_errors.no_errors(pt), (b,))
        k0 = jax.random.split(jax.random.fold_in(k_drift, TOOLS_KEY), 3)
        drift0 = jnp.concatenate([camera_errors.drift_start(k0[i], b, p) for i, p in enumerate((pn, pt, pt))], -1)

        def view(frame, ee, q, drift):
            """Frame ``frame``'s needle and tool as the policy sees them (the drifts ``[B, 18]`` of
            the needle and both tools advanced to it, unless ``frames`` holds one frame), and
            where the tool's kinematics say it is (what a camera-seen tool's mean is moved by
            between frames)."""
            if frames != "one":
                kd = jax.random.split(jax.random.fold_in(k_drift, frame), 3)
                drift = jnp.concatenate(
                    [
                        camera_errors.drift_next(kd[i], drift[:, 6 * i : 6 * i + 6], p)
                        for i, p in enumerate((pn, pt, pt))
                    ],
                    -1,
                )
            k_frame = jax.random.fold_in(key, frame)
            estimate = camera_errors.frame(k_frame, biased, drift[:, :6], pn, depth)
            if camera:
                k_g, k_r = jax.random.split(jax.random.fold_in(k_tools, frame))
                keys = ((tool_bias[0], k_g), (tool_bias[1], k_r))
                seen = camera_errors.camera_frame(keys, estimate, ee, drift[:, 6:], pt, depth)
            else:
                seen = kinematic_view(arms, estimate, ee, q)
            return seen, (ee if q is None else kinematic_pose(q)), drift

        def fuse_frame(info, frame, ee, q, rows=None):
            """``info`` with frame ``frame`` fused into the ``rows`` (default all) that take it: the
            needle's running sum, the tool's view (the view so far moved as the kinematics say, and
            averaged with this frame's), the drifts, the count; and this frame's own view."""
            (frame_needle, frame_tool), kin, drift = view(frame, ee, q, info["drift"])
            total = estimates.fuse(info["needle_total"], frame_needle, biased)
            count = info["frames"]  # the frames fused before this one
            tool = frame_tool
            if camera and frames != "each":
                moved = propagate(info["ee_seen"], info["kinematics"], kin)
                if fused:
                    tool = jnp.where(count[:, None] > 0, average(moved, count, frame_tool), frame_tool)
                else:  # one frame, then the plan's own motion
                    tool = jnp.where(count[:, None] > 0, moved, frame_tool)
                tool = jnp.where(exact_tools[:, None], frame_tool, tool)  # a camera that sees the tool exactly
            new = {"needle_total": total, "ee_seen": tool, "kinematics": kin, "drift": drift, "frames": count + 1}
            if rows is not None:
                new = {k: jnp.where(rows.reshape((-1,) + (1,) * (v.ndim - 1)), v, info[k]) for k, v in new.items()}
            return {**info, **new}, frame_needle

        def unsure(info, stop_tol):
            """``[B]`` whether a row's fused view is still too uncertain to stop on: twice its
            standard deviation on the worst axis (the camera's depth; the needle's and, seen by the
            camera, the tool's errors less their biases, from the model's known sizes) exceeds the
            room the stop tolerance keeps inside the success tolerance."""
            n = info["frames"]
            var = camera_errors.fused_variance(n, pn) + (camera_errors.fused_variance(n, pt) if camera else 0.0)
            room = success_tol[0] - stop_tol[0]
            return 2.0 * depth[0] * jnp.sqrt(var) * 1e-3 > room

        def seen_needle(info, frame_needle):
            return estimates.mean_pose(info["needle_total"], info["frames"][:, None]) if fused else frame_needle

        # the rule's per-row data rides in state.info: the fused frames and their count, the view acted
        # on, where the kinematics put the tool, its readings, the drifts, which rows act at this step
        # (the shield works on those alone) and which have looked (before the last moves, at the goal)
        info = {
            **state.info,
            "needle_total": jnp.zeros((b, 7)),
            "needle_seen": needle,
            "ee_seen": ee0,
            "kinematics": ee0 if q0 is None else kinematic_pose(q0),
            "drift": drift0,
            "frames": jnp.zeros(b),
            "looked": jnp.zeros(b, jnp.int32),
            "looked_near": jnp.zeros(b, bool),
            "looked_stop": jnp.zeros(b, bool),
            "acting": jnp.ones(b, bool),
            "start_seen": jnp.concatenate([needle, ee0], -1),
        }
        if joints:
            info["readings"] = q0
        if fused:  # frames before the first step (the tool holds still): keys beyond the horizon's
            for i in range(warmup - 1):
                info, _ = fuse_frame(info, horizon + 2 + i, ee0, q0)
        state = state.replace(info=info)

        def stop(state, t, live):
            """This step's frame (and, with ``look``, the frames looked at): stop where the view says
            the goal is reached (a success where the true poses agree)."""
            es = state.pipeline_state
            ee = jnp.concatenate([es.ee_pos, es.ee_quat], -1)
            q = readings(arms, ee, state.info["readings"]) if joints else None
            # the rows that ended keep their counts (a row's frames are those it fused while live)
            info, frame_needle = fuse_frame(state.info, 0 if frames == "one" else t, ee, q, live)
            seen = seen_needle(info, frame_needle)
            viewed = _with_needle(state, seen, info["ee_seen"])
            stopping = _at_goal(env, viewed, seen, stop_tol)
            if look:  # hold still and fuse frames while the spread leaves no room, at most `look` a look
                near = _at_goal(env, viewed, seen, tuple(NEAR * x for x in stop_tol))
                first = (stopping & ~info["looked_stop"]) | (near & ~info["looked_near"])
                want = live & (t < horizon) & first & unsure(info, stop_tol)

                def more(c):
                    return (c[0] < look) & jnp.any(c[2])

                def one_frame(c):
                    i, info, want = c
                    info = fuse_frame(info, LOOK_KEY + t * look + i, ee, q, want)[0]
                    info["looked"] = info["looked"] + want
                    return i + 1, info, want & unsure(info, stop_tol)

                info = jax.lax.while_loop(more, one_frame, (0, info, want))[1]
                info["looked_near"] = info["looked_near"] | (live & near)
                info["looked_stop"] = info["looked_stop"] | (live & stopping)
                seen = seen_needle(info, frame_needle)
                stopping = _at_goal(env, _with_needle(state, seen, info["ee_seen"]), seen, stop_tol)
            acting = live & ~stopping & (t < horizon)
            # the view the first move is made on: what the jaw's opening is decided from (closed_loop_host)
            start_seen = jnp.where(t == 0, jnp.concatenate([seen, info["ee_seen"]], -1), info["start_seen"])
            info = {**info, "needle_seen": seen, "acting": acting, "start_seen": start_seen}
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
            a = jnp.where(jnp.all(info["ee_seen"] == ee, -1, keepdims=True), a, done)
            if not env.opens:
                return a
            # the jaws: open where the view leaves the sweep its margin (the loop knows their opening)
            want = jnp.float32(env.config.jaw_open_deg)
            needle_radius = seen.pipeline_state.needle_radius
            sd = camera_errors.view_sd_mm(
                info["frames"], pn, pt, depth[0], reach, needle_radius, info["ee_seen"][:, :3]
            )
            room = jax.vmap(env.opening_room, in_axes=(0, None))(seen.pipeline_state, want)
            opening = info["acting"] & (es.jaw_deg < want) & (room >= env.jaw_margin + jaw_sigmas * sd * 1e-3)
            return jnp.concatenate([a, jnp.where(opening, want, es.jaw_deg)[:, None]], -1)

        def pose(state, a, nxt):  # and the jaws' opening after the step
            es = nxt.pipeline_state
            return jnp.concatenate([es.ee_pos, es.ee_quat], axis=1), es.jaw_deg

        out = rollout(env, act, state, max_steps=horizon, stop=stop, trace=pose, step=jax.vmap(move))
        # [B, horizon + 1, 7]: the start, the pose after each step, the last one held after the end
        trace = jnp.concatenate([start[None].astype(out.trace[0].dtype), out.trace[0]], axis=0)
        held = jnp.minimum(jnp.arange(horizon + 1)[:, None], out.steps[None, :])
        poses = jnp.take_along_axis(trace, held[..., None], axis=0).transpose(1, 0, 2)
        info = out.state.info
        jaws = jaw_opening.outputs(env, state, poses, out.trace[1], out.steps)
        return {
            **jaws,
            "start_valid": out.start_valid,
            "success": out.success,
            "collision": out.collision,
            "time_out": out.time_out,
            "stopped": out.stopped,
            "steps": out.steps.astype(jnp.int32),
            "frames": info["frames"].astype(jnp.int32),
            "looked": info["looked"].astype(jnp.int32),
            "start_seen": info["start_seen"],
            "poses": poses,
        }

    return jax.jit(run)


def make_stepper(env: RegraspEnv, apply: Callable, shield: bool, stop_scale: float = 1.0):
    """``step(weights, needle, ee, goal, t, radii=None, jaw_deg=None) -> (action, next_ee, at_goal,
    jaw_deg)`` (jitted, ``[B, 7]`` poses in e_g; ``radii`` as :func:`make_executor`'s): one
    closed-loop step from the current estimates. ``at_goal`` (within
    ``stop_scale`` of the success tolerances on the estimate) rows should stop (their action is zero
    and ``next_ee`` is ``ee``). ``jaw_deg`` ``[B]``: the jaws' opening now (None: the scene's); the
    one returned is the opening the step moves with (where the policy opens them on the way, the
    environment's rule on the estimate; a row at its goal keeps its own)."""

    def one(weights, needle, ee, goal, t, radii=None, jaw_deg=None):
        episode = Episode.from_poses(needle, ee, goal, radii)
        state = jax.vmap(env.reset_from)(episode)
        if jaw_deg is not None:  # the jaws where the loop has them (issue 67)
            state = state.replace(pipeline_state=state.pipeline_state.replace(jaw_deg=jaw_deg))
        done = _at_goal(env, state, needle, tolerances(env.config, stop_scale))
        a = jnp.where(done[:, None], 0.0, choose_action(env, apply, weights, state, t, shield, ~done))
        es = jax.vmap(env.step)(state, a).pipeline_state
        nxt = jnp.where(done[:, None], ee, jnp.concatenate([es.ee_pos, es.ee_quat], axis=1))
        jaws = jnp.where(done, state.pipeline_state.jaw_deg, es.jaw_deg)
        return jnp.clip(a, -1.0, 1.0), nxt, done, jaws

    return jax.jit(one)
