"""Planning with a loaded policy: :class:`Plan` and the functions behind ``Policy.plan`` and
``Policy.plan_from_camera``.

A plan rolls the deterministic policy out in the environment it was trained in (kinematics and
exact collision checks) until success, collision or the horizon, shielded by default, and returns
the trajectory. Batches, the GPU and camera-frame queries run the jitted program
(:mod:`regrasp_mjx.inference.planner`); one query on the CPU runs the same rollout compiled with numba
(:mod:`regrasp_mjx.inference.lean_planner`), its input checks, default goal and grasp-library distance
included, in one call.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core import geometry
from regrasp_mjx.envs import host
from regrasp_mjx.inference import jaw_opening
from regrasp_mjx.inference.grasps import GraspLibrary
from regrasp_mjx.inference.planner import PlanArrays, goal_pose_in_needle
from regrasp_mjx.inference.queries import (
    OOD_WARN_DISTANCE,
    START_WARN_MM,
    PoseError,
    TaskSpec,
    batch_poses,
    check_poses,
    nearest_grasps,
    start_distance_mm,
    warn_far_grasps,
    warn_far_starts,
)
from regrasp_mjx.robot import dvrk, psm_joints

ENGINES = ("auto", "jax", "lean")  # Policy.plan's planning programs
NO_LIBRARY = (
    np.zeros((0, 3)),
    np.zeros((0, 4)),
    np.zeros((7, 0), np.float32),
)  # the lean query's grasp library when not checked


def auto_engine(queries: int, policy: Any = None) -> str:
    """What ``Policy.plan(engine="auto")`` runs ``queries`` queries with: the lean numba rollout for
    one query when JAX runs on the CPU, the jitted JAX program otherwise. Every policy alike: the lean
    rollout carries jaws that open on the way as the environment opens them (``policy`` is kept for
    the callers that name it)."""
    return "lean" if queries == 1 and jax.default_backend() == "cpu" else "jax"


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
      poses_camera: the same poses in the camera frame (only from ``Policy.plan_from_camera``),
        the same shape as ``poses`` (padded with the last pose): the trajectory itself is
        ``trajectory("camera")``, ``steps + 1`` rows.
      nearest_grasp_distance: distance of the needle pose to the nearest of the valid-grasp library
        (``regrasp_mjx.grasps``; mm + deg / 5), when checked.
      joints: with ``plan_from_camera(..., psm=...)``, the regrasping PSM's
        :class:`~regrasp_mjx.robot.psm_joints.JointTrajectory` of the valid poses (a list of them for a batch);
        for a policy whose jaws open on the way, with the jaw's track (``joints.jaw``: where they open).
      grasping_joints: likewise the grasping PSM's :class:`~regrasp_mjx.robot.dvrk.IKResult` at its pose.
      motion: with ``plan_from_camera(..., psm=..., timed=True)``, the regrasping PSM's motion
        (:class:`~regrasp_mjx.robot.executed_motion.TimedPlan`: a 1-kHz joint trajectory at the dVRK's limits,
        re-checked, or why it was refused; a list of them for a batch).
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
    motion: Any = None

    def __repr__(self) -> str:
        ok = np.atleast_1d(self.success)
        if ok.size == 1 and np.ndim(self.success) == 0:
            return (
                f"Plan(success={bool(self.success)}, steps={int(self.steps)}, "
                f"path_length_mm={float(self.path_length_mm):.2f})"
            )
        return f"Plan({ok.size} queries: success {ok.mean():.3f}, collision {np.mean(self.collision):.3f})"

    def trajectory(self, frame: str = "eg", query: int | None = None) -> np.ndarray:
        """The valid poses of one plan (``steps + 1`` rows), in ``eg`` or ``camera`` frame: this
        plan's, or of a batch's ``query``-th."""
        if frame not in ("eg", "camera"):
            raise ValueError(f"frame={frame!r} is not accepted: 'eg' or 'camera'")
        poses = self.poses if frame == "eg" else self.poses_camera
        if poses is None:
            raise ValueError("this plan has no camera-frame poses: plan_from_camera makes them")
        if poses.ndim == 2:
            if query not in (None, 0):
                raise ValueError(f"query={query!r} is not accepted: this Plan holds one query")
            return poses[: int(self.steps) + 1]
        if query is None or not (isinstance(query, (int, np.integer)) and 0 <= query < len(poses)):
            raise ValueError(
                f"query={query!r} is not accepted: this Plan holds {len(poses)} queries; trajectory(query=i) "
                f"gives query i's (0 <= i < {len(poses)})"
            )
        return poses[query][: int(self.steps[query]) + 1]


def plan(
    policy: Any,
    needle: Any,
    start: Any,
    goal: Any = None,
    *,
    check_grasp: bool = True,
    shield: bool = True,
    engine: str = "auto",
    **task: Any,
) -> Plan:
    """Plans with ``policy`` from poses in the grasping end-effector frame e_g (7-vectors, or batches
    ``[B, 7]``) (``Policy.plan``).

    ``goal`` defaults to the goal grasp of ``task`` (:class:`~regrasp_mjx.inference.queries.TaskSpec`'s
    keywords: ``goal_alpha_rad``, ``goal_depth_mm``, ``goal_theta_rad``, ``goal_phi_rad``,
    ``needle_radius_mm``, ``wire_radius_mm``; each None, a scalar or one value per query; None: the
    task's goal grasp, the middle of the trained depth range, the scene's needle, the paper's 5.4 and
    0.25 mm) on this needle; each value must lie in what the policy was trained for
    (``Policy.trained_ranges``): a specialist takes its one goal grasp and needle, a general policy
    their ranges. ``shield`` replaces a policy action that would collide by the first
    collision-free alternative (:func:`~regrasp_mjx.envs.shield.shield_candidates`); ``shield=False``
    rolls the policy out as trained. ``check_grasp``: warn when a paper-task policy's needle pose is
    far from every valid grasp of the library (its distance in ``Plan.nearest_grasp_distance``).
    Warns about starts implausibly far from their needle. Raises :class:`PoseError` on bad input.

    ``engine``: ``"jax"`` runs the jitted program (:mod:`regrasp_mjx.inference.planner`; any batch, any
    device); ``"lean"`` the same rollout compiled with numba for one query on the CPU
    (:mod:`regrasp_mjx.inference.lean_planner`, several times faster there; it gives the JAX path's verdicts,
    and its actions to float32 rounding); ``"auto"`` (default) takes the lean one for a single
    query when JAX runs on the CPU."""
    if engine not in ENGINES:
        raise ValueError(f"engine={engine!r} is not accepted; accepted: {', '.join(map(repr, ENGINES))}")
    for name, flag in (("shield", shield), ("check_grasp", check_grasp)):
        if not isinstance(flag, (bool, np.bool_)):
            raise ValueError(f"{name}={flag!r} is not accepted: True or False")
    if engine != "jax":
        one = _lean_one(policy, needle, start, goal, task, check_grasp, shield)
        if one is not None:  # else a batch, the JAX engine, or input the checks below name
            return one
    spec = TaskSpec.of(task)
    (needle, start), single = batch_poses(needle=needle, start=start)
    grasp, radii = policy.task_ranges.resolve(len(needle), spec)
    if engine == "auto":
        engine = auto_engine(len(needle), policy)
    if engine == "lean" and len(needle) != 1:
        raise ValueError(f"engine='lean' plans one query at a time; got {len(needle)}: use engine='jax'")
    goal = checked_goals(needle, goal, grasp, radii)
    nearest = nearest_grasps(needle) if check_grasp and not policy.general else None
    if nearest is not None:
        warn_far_grasps(nearest)
    warn_far_starts(start_distance_mm(needle, start))
    if engine == "lean":  # a batch of one
        task = np.concatenate([grasp[0], radii[0]])
        one = policy.lean(shield)(needle[0], start[0], goal[0], task, NO_LIBRARY)
        if one.status:  # checked above in float64 already: the compiled check must agree
            raise PoseError(f"pose {('needle', 'start', 'goal')[one.status - 1]} failed the lean planner's check")
        return _lean_plan(one, single, nearest)  # one query's fields as numpy scalars, a batch's as arrays
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731  (numpy in: the fastest dispatch)
    out = policy.program((False, shield))(f32(needle), f32(start), f32(goal), f32(radii))
    return _finish(out, single, nearest)


def _lean_one(policy: Any, needle: Any, start: Any, goal: Any, task: dict, check_grasp: bool, shield: bool):
    """One query (7-vectors, ``task`` the goal grasp and needle keywords as given) on the lean path
    in one compiled call, or None when the input is not one query, the JAX engine runs, or a check
    failed (the caller's checks then say why, the poses first). Plain Python around the call: each
    numpy call here would cost a microsecond of a 50 us plan."""
    try:
        poses = [x if type(x) is np.ndarray or x is None else np.asarray(x) for x in (needle, start, goal)]
    except ValueError:  # ragged: the caller's checks name it
        return None
    if any(x is not None and x.shape != (7,) for x in poses) or auto_engine(1, policy) != "lean":
        return None
    vector = policy.task_ranges.keywords_vector(task)
    if vector is None:
        return None
    checked = check_grasp and not policy.general
    library = GraspLibrary.default().unit_arrays if checked else NO_LIBRARY
    one = policy.lean(shield)(*poses, vector, library)
    if one.status:
        return None
    nearest = np.float64(one.nearest) if checked else None
    if checked and nearest > OOD_WARN_DISTANCE:
        warn_far_grasps(np.array([nearest]), stacklevel=5)
    if one.start_mm > START_WARN_MM:
        warn_far_starts(np.array([one.start_mm]), stacklevel=5)
    return _lean_plan(one, True, nearest)


def _lean_plan(one: Any, single: bool, nearest: Any = None) -> Plan:
    """A :class:`Plan` of the lean planner's :class:`~regrasp_mjx.inference.lean_planner.LeanResult` (numpy
    scalars for one query, as the JAX path's single plans hold, or arrays of one)."""
    valid, success, collision, time_out, steps, length = one.outcome[:6]
    fields = (_BOOL[success > 0], _BOOL[collision > 0], _BOOL[time_out > 0], _BOOL[valid > 0])
    fields += (np.int64(steps), np.float32(length * 1e3))
    if single:
        return _made(*fields, one.poses, one.actions, nearest)
    return Plan(*(np.array([x]) for x in fields), one.poses[None], one.actions[None], nearest_grasp_distance=nearest)


_BOOL = (np.False_, np.True_)  # indexed by a Python bool: numpy's own, without a constructor call


def _made(success, collision, time_out, start_valid, steps, length, poses, actions, nearest) -> Plan:
    """``Plan(..., nearest_grasp_distance=nearest)`` without the frozen dataclass's ``__init__``
    (it sets each of the 12 fields through ``object.__setattr__``: 3 us of a 50 us plan)."""
    plan = object.__new__(Plan)
    d = plan.__dict__
    d["success"], d["collision"], d["time_out"], d["start_valid"] = success, collision, time_out, start_valid
    d["steps"], d["path_length_mm"], d["poses"], d["actions"] = steps, length, poses, actions
    d["poses_camera"], d["nearest_grasp_distance"], d["joints"], d["grasping_joints"] = None, nearest, None, None
    return plan


def _first(x):
    return None if x is None else x[0]


def _finish(out: PlanArrays, single: bool, nearest) -> Plan:
    o = out.outcome
    pick = _first if single else (lambda x: x)  # one query: its row of every field  # noqa: E731
    # the program returns the trajectories cut after the longest plan, float32: no copy here
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


def checked_goals(needle: np.ndarray, goal: Any, grasp: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Goals ``[n, 7]`` for checked needles ``[n, 7]``: ``goal`` checked, or by default the goal grasps
    ``[n, 4]`` on the needles of radii ``[n, 2]``; a :class:`PoseError` when the batch sizes differ."""
    goal = np.atleast_2d(check_poses("goal", default_goal(needle, grasp, radii) if goal is None else goal))
    if goal.shape != needle.shape:
        raise PoseError(f"goal {goal.shape} and needle {needle.shape} poses differ in batch size")
    return goal


def default_goal(needle: np.ndarray, grasp: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """The goal end-effector poses ``[n, 7]`` (e_g) of goal grasps ``[n, 4]`` on needles ``[n, 7]``
    of radii ``[n, 2]`` [m]."""
    goal = geometry.compose(
        (jnp.asarray(needle[:, :3]), jnp.asarray(needle[:, 3:])),
        goal_pose_in_needle(jnp.asarray(grasp), jnp.asarray(radii[:, 0])),
    )
    return np.concatenate([np.asarray(goal[0]), np.asarray(goal[1])], axis=1)


def plan_from_camera(
    policy: Any,
    grasping_ee: Any,
    regrasping_ee: Any,
    needle: Any,
    *,
    check_grasp: bool = True,
    shield: bool = True,
    psm: dict | None = None,
    respect_limits: bool = True,
    timed: bool = False,
    **task: Any,
) -> Plan:
    """Plans with ``policy`` from three camera-frame poses (7-vectors or ``[B, 7]``), as on a real
    dVRK (SPEC "Deployment") (``Policy.plan_from_camera``); the plan's poses come in the e_g frame
    and the camera frame. ``shield``, ``check_grasp`` and the task keywords as in :func:`plan`.

    ``psm``: ``{"regrasping_base": pose, "grasping_base": pose}`` (camera-frame 7-vectors or 4x4
    of each PSM's base, i.e. remote-centre-of-motion, frame; ``grasping_base`` optional). The
    plan then also holds the regrasping arm's joint trajectory with a per-pose joint-limit
    verdict (``Plan.joints``) and the grasping arm's joints at its pose (``Plan.grasping_joints``)
    from :mod:`regrasp_mjx.robot.dvrk`; out-of-limit poses are reported, not changed. With
    ``respect_limits`` (and the shield) the shield also replaces an action whose end pose would
    leave the regrasping arm's joint limits, as it replaces a colliding one. With ``timed`` (and
    ``psm``) each plan's motion on the arm, timed at the dVRK's limits and re-checked where it goes,
    is ``Plan.motion`` (:mod:`regrasp_mjx.robot.executed_motion`)."""
    spec = TaskSpec.of(task)
    (c_eg, c_er, c_n), single = batch_poses(grasping_ee=grasping_ee, regrasping_ee=regrasping_ee, needle=needle)
    grasp, radii = policy.task_ranges.resolve(len(c_eg), spec)
    nearest = None
    if check_grasp and not policy.general:
        rel = [host.relative(e[:3], e[3:], n[:3], n[3:]) for e, n in zip(c_eg, c_n)]
        nearest = nearest_grasps(np.concatenate([np.stack([r[0] for r in rel]), np.stack([r[1] for r in rel])], axis=1))
        warn_far_grasps(nearest)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731  (numpy in: the fastest dispatch)
    base_inv = None
    if timed and psm is None:
        raise PoseError("timed=True is not accepted without psm: the motion timed is the regrasping PSM's")
    if psm is not None:
        unknown = set(psm) - {"regrasping_base", "grasping_base"}
        if "regrasping_base" not in psm or unknown:
            raise PoseError(f"psm={sorted(psm)} is not accepted: a dict with 'regrasping_base' (and 'grasping_base')")
        for key in ("regrasping_base", "grasping_base"):  # before the plan: NaN or a non-rigid 4x4 named
            if psm.get(key) is not None:
                try:
                    dvrk.as_matrix(psm[key], f"psm[{key!r}]")
                except ValueError as err:
                    raise PoseError(str(err)) from None
        if respect_limits and shield:  # the base frame's inverse in e_g, per query
            base = np.linalg.inv(dvrk.as_matrix(psm["regrasping_base"], "psm['regrasping_base']"))
            base_inv = f32([base @ dvrk.pose_matrix(e) for e in c_eg])
    out = policy.program((True, shield))(f32(c_eg), f32(c_er), f32(c_n), f32(grasp), f32(radii), base_inv)
    result = _finish(out, single, nearest)
    return result if psm is None else _with_joints(result, psm, c_eg, c_n, radii, single, policy, timed)


def _with_joints(plan: Plan, psm: dict, c_eg, c_n, radii, single: bool, policy: Any, timed: bool) -> Plan:
    """``plan`` with the regrasping PSM's joints (and, for a policy whose jaws open on the way, the
    jaw's track: the pose each plan opens them at, as its environment found it), the grasping PSM's,
    and with ``timed`` the timed, re-checked motion."""
    steps = np.atleast_1d(plan.steps)
    cam = plan.poses_camera[None] if single else plan.poses_camera
    joints = [psm_joints.joint_trajectory(psm["regrasping_base"], cam[i][: steps[i] + 1]) for i in range(len(cam))]
    if policy.env_config.jaw_open_deg is not None:
        opens = _opening_poses(policy, plan, c_eg, c_n, radii, single)
        joints = [
            dataclasses.replace(j, jaw=psm_joints.JawTrack.of(policy.env_config, opens[i], steps[i] + 1))
            for i, j in enumerate(joints)
        ]
    motion = None
    if timed:
        # here: toppra (and the matplotlib it imports) load in ~0.7 s, only where a timed motion is asked
        from regrasp_mjx.robot.executed_motion import motion_or_reason

        ok = np.atleast_1d(plan.success)
        motion = [motion_or_reason(policy, j, bool(ok[i]), c_eg[i], c_n[i], psm) for i, j in enumerate(joints)]
    grasping = None
    if psm.get("grasping_base") is not None:
        base_inv = np.linalg.inv(dvrk.as_matrix(psm["grasping_base"], "psm['grasping_base']"))
        grasping = [dvrk.inverse_kinematics(base_inv @ dvrk.pose_matrix(e)) for e in c_eg]
    if single:
        joints, grasping = joints[0], None if grasping is None else grasping[0]
        motion = None if motion is None else motion[0]
    return dataclasses.replace(plan, joints=joints, grasping_joints=grasping, motion=motion)


def _opening_poses(policy: Any, plan: Plan, c_eg, c_n, radii, single: bool) -> np.ndarray:
    """Each plan's pose where the jaws open (-1: never), :func:`~regrasp_mjx.inference.jaw_opening.opening_steps`
    on its e_g poses around the needle seen from the grasping tool."""
    rel = [host.relative(e[:3], e[3:], n[:3], n[3:]) for e, n in zip(c_eg, c_n)]
    needle = np.stack([np.r_[p, q] for p, q in rel])
    poses = plan.poses[None] if single else plan.poses
    return jaw_opening.opening_steps(policy, needle, poses, np.atleast_1d(plan.steps), radii)
