"""A plan's executed motion on a dVRK PSM, checked and repaired: the timed joint trajectory
(:mod:`regrasp_mjx.robot.psm_timing`) posed by forward kinematics and re-checked against the needle
and the other tool, waypoints inserted where it collides or leaves the joint limits, else refused.

The PSM's controller streams joint positions (``servo_jp``) at its rate, and a remote-centre arm's
tool tip does not move on the checked Cartesian step when its joints are interpolated, so the
executed motion is checked where it goes, not where the plan's steps went:

- :func:`check_motion` poses the tool by forward kinematics at every sample and tests each 1-ms piece
  with the lean collision test along its whole motion (:class:`~regrasp_mjx.envs.lean_checker.LeanChecker`),
  the margin raised by how far the arc of forward kinematics can leave the piece's chord.
- :func:`time_plan` times (:func:`~regrasp_mjx.robot.psm_timing.time_joints`) and checks a plan from
  ``Policy.plan_from_camera(..., psm=...)``, :func:`time_executed` a closed loop's executed poses; where
  a piece collides it inserts the Cartesian midpoint of the step around it as a waypoint (its joints
  by inverse kinematics, nearest the previous ones) and times again, at most :data:`MAX_INSERTIONS`
  times, and otherwise refuses the plan with the time and step that collide: never a silent
  collision.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from regrasp_mjx.envs.host import quat_conj, quat_from_rotvec, quat_mul, quat_to_rotvec
from regrasp_mjx.envs.lean_checker import LeanChecker
from regrasp_mjx.robot import dvrk, psm_joints
from regrasp_mjx.robot.psm_joints import JointTrajectory
from regrasp_mjx.robot.psm_timing import RATE_HZ, TimedTrajectory, time_joints
from regrasp_mjx.world.scene import load_scene

MAX_INSERTIONS = 8
TOOL_REACH = 0.3  # m: farther than any point of the tool's capsules from the RCM (insertion <= 0.24 m)


@dataclasses.dataclass(frozen=True)
class MotionCheck:
    """The executed motion's verdict: ``collides``, the first colliding sample ``index`` and its
    time ``t_s`` (None when clear), ``within_limits`` (every sample's joints within the PSM's
    limits) and ``chord_margin_m``, what the test's margin was raised by."""

    collides: bool
    index: int | None
    t_s: float | None
    within_limits: bool
    chord_margin_m: float


def check_motion(timed: TimedTrajectory, base_in_eg, needle_in_eg, policy) -> MotionCheck:
    """Tests the executed motion of ``timed`` (the regrasping PSM whose base frame is ``base_in_eg``,
    4x4 or 7-vector in the grasping end-effector frame e_g) against the needle at ``needle_in_eg``
    (7-vector, e_g) and the grasping tool, with ``policy``'s scene and clearance margin.

    Each piece between two samples is tested along its whole motion (position linear, orientation
    slerped) with the margin raised by how far the forward-kinematics arc can leave that chord over
    one sample period: ``a dt^2 / 8`` for the fastest acceleration ``a`` of any tool point, bounded by
    the joints' accelerations and velocities times :data:`TOOL_REACH`."""
    base = dvrk.as_matrix(base_in_eg, "base_in_eg")
    poses = tool_poses(base, timed.q)
    dt = 1.0 / timed.rate_hz
    qd, qdd = np.abs(timed.qd), np.abs(timed.qdd)
    angular_v = qd[:, [0, 1, 3, 4, 5]].sum(1)
    accel = (
        qdd[:, 2] + TOOL_REACH * qdd[:, [0, 1, 3, 4, 5]].sum(1) + TOOL_REACH * angular_v**2 + 2 * qd[:, 2] * angular_v
    )
    chord = float(accel.max() * dt * dt / 8.0)
    env = policy.env_config
    checker = LeanChecker(load_scene(env.scene), env.clearance_mm + chord * 1e3)
    placed = checker.place(np.asarray(needle_in_eg, np.float64))
    hit = None
    if checker.pose_collides(placed, *poses[0]):
        hit = 0
    else:
        for i in range(1, len(poses)):
            if checker.motion_collides(placed, poses[i - 1], poses[i]):
                hit = i
                break
    within = bool(np.all((timed.q >= dvrk.Q_MIN - 1e-9) & (timed.q <= dvrk.Q_MAX + 1e-9)))
    return MotionCheck(hit is not None, hit, None if hit is None else float(timed.t[hit]), within, chord)


@dataclasses.dataclass(frozen=True)
class TimedPlan:
    """A plan's motion on the arm: the ``trajectory``, its ``check`` (clear), and ``inserted``: the
    waypoints added where the first timing's motion left the checked steps; or, where it could not
    be timed (``Plan.motion`` of ``plan_from_camera(..., timed=True)``), ``refused``: why, and
    neither trajectory nor check."""

    trajectory: TimedTrajectory | None
    check: MotionCheck | None
    inserted: int = 0
    refused: str | None = None

    @property
    def ok(self) -> bool:
        return self.refused is None


class MotionRefused(ValueError):
    """A plan whose executed motion collides or leaves the joint limits, with where and why."""


def time_plan(
    policy, plan, camera_eg, needle, psm: dict, query: int | None = None, rate_hz: float = RATE_HZ
) -> TimedPlan:
    """The timed, re-checked joint trajectory of one plan of ``policy.plan_from_camera(camera_eg, ...,
    needle, psm=psm)`` (the same camera-frame ``camera_eg`` and ``needle``; ``query``: which one of a
    batch). Raises :class:`MotionRefused` where the plan did not reach the goal, a pose is outside
    the joint limits, or the motion still collides after :data:`MAX_INSERTIONS` inserted waypoints."""
    if plan.joints is None:
        raise MotionRefused("the plan has no joints: make it with plan_from_camera(..., psm=...)")
    i = 0 if query is None else query
    joints: JointTrajectory = plan.joints if query is None else plan.joints[query]
    c_eg, c_n = (np.asarray(x, np.float64).reshape(-1, 7) for x in (camera_eg, needle))
    return time_query(policy, joints, bool(np.atleast_1d(plan.success)[i]), c_eg[i], c_n[i], psm, rate_hz)


def time_query(policy, joints: JointTrajectory, success: bool, camera_eg, needle, psm: dict, rate_hz=RATE_HZ):
    """:func:`time_plan` of one query's ``joints`` and ``success`` (camera-frame 7-vectors)."""
    if not success:
        raise MotionRefused("the plan did not reach the goal: no motion to time")
    _require_reachable(joints)
    eg_inv = np.linalg.inv(dvrk.as_matrix(camera_eg, "camera_eg"))
    base = eg_inv @ dvrk.as_matrix(psm["regrasping_base"], "psm['regrasping_base']")
    n = eg_inv @ dvrk.as_matrix(needle, "needle")
    return time_waypoints(joints.q, base, np.r_[n[:3, 3], _quat(n[:3, :3])], policy, rate_hz)


def _require_reachable(joints: JointTrajectory) -> None:
    """:class:`MotionRefused`, naming the poses and the first one's limits, where a pose is out of reach."""
    if not joints.all_reachable:
        bad = [k for k, ok in enumerate(joints.reachable) if not ok]
        raise MotionRefused(f"poses {bad} are outside the PSM's joint limits ({', '.join(joints.violations[bad[0]])})")


def motion_or_reason(policy, joints: JointTrajectory, success: bool, camera_eg, needle, psm: dict) -> TimedPlan:
    """:func:`time_query`, a refusal returned as ``TimedPlan(refused=why)`` instead of raised."""
    try:
        return time_query(policy, joints, success, camera_eg, needle, psm)
    except MotionRefused as why:
        return TimedPlan(None, None, 0, str(why))


def time_executed(policy, poses, needle_in_eg, base_in_eg, rate_hz: float = RATE_HZ) -> TimedPlan:
    """The timed, re-checked joint trajectory of a closed loop's executed poses (``execute(...)["poses"]``
    of one row up to its ``steps``: 7-vectors ``[S + 1, 7]`` in e_g) on the regrasping PSM whose base
    is ``base_in_eg``, against the true needle ``needle_in_eg``: the motion the arm makes through the
    steps the loop chose (:func:`time_waypoints`). Raises :class:`MotionRefused` where a pose is
    outside the joint limits or the motion cannot be made clear."""
    joints = psm_joints.joint_trajectory(base_in_eg, poses)
    _require_reachable(joints)
    base = dvrk.as_matrix(base_in_eg, "base_in_eg")
    return time_waypoints(joints.q, base, np.asarray(needle_in_eg, np.float64), policy, rate_hz)


def time_waypoints(waypoints, base_in_eg, needle_in_eg, policy, rate_hz: float = RATE_HZ) -> TimedPlan:
    """:func:`time_joints` of joint ``waypoints`` [W, 6], its motion checked by :func:`check_motion`;
    where it collides or leaves the limits, the Cartesian midpoint of the step around the first bad
    sample is inserted as a waypoint and the whole is timed again (at most :data:`MAX_INSERTIONS`
    times), else :class:`MotionRefused` says where."""
    waypoints = np.asarray(waypoints, np.float64).copy()
    for inserted in range(MAX_INSERTIONS + 1):
        timed = time_joints(waypoints, rate_hz)
        check = check_motion(timed, base_in_eg, needle_in_eg, policy)
        if not check.collides and check.within_limits:
            return TimedPlan(timed, check, inserted)
        if inserted < MAX_INSERTIONS:
            waypoints = _insert_midpoint(waypoints, timed, check)
    where = f"collides at {check.t_s:.3f} s" if check.collides else "leaves the joint limits"
    raise MotionRefused(
        f"the arm's joint-space motion {where} after {MAX_INSERTIONS} inserted waypoints; the plan is refused "
        "(its Cartesian steps are collision-free, the arm's interpolation of them is not)"
    )


def _insert_midpoint(waypoints: np.ndarray, timed: TimedTrajectory, check: MotionCheck) -> np.ndarray:
    """The waypoints with the Cartesian midpoint of the segment around the first bad sample added."""
    bad = check.index if check.collides else int(np.argmax(np.any((timed.q < dvrk.Q_MIN) | (timed.q > dvrk.Q_MAX), 1)))
    # the segment: the last waypoint the trajectory has passed by the bad sample
    passed = [int(np.argmin(np.abs(timed.q - w).sum(1))) for w in waypoints]
    seg = max(0, min(len(waypoints) - 2, sum(1 for p in passed if p <= bad) - 1))
    a, b = dvrk.forward_kinematics(waypoints[seg]), dvrk.forward_kinematics(waypoints[seg + 1])
    mid = np.eye(4)
    mid[:3, 3] = (a[:3, 3] + b[:3, 3]) / 2
    mid[:3, :3] = _slerp_half(a[:3, :3], b[:3, :3])
    q_mid = dvrk.inverse_kinematics(mid, waypoints[seg]).q
    return np.insert(waypoints, seg + 1, q_mid, axis=0)


def _slerp_half(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """The rotation halfway from ``ra`` to ``rb`` along the shorter arc."""
    qa, qb = _quat(ra), _quat(rb)
    half = quat_mul(qa, quat_from_rotvec(quat_to_rotvec(quat_mul(quat_conj(qa), qb)) / 2.0))
    return dvrk.pose_matrix(np.r_[0.0, 0.0, 0.0, half])[:3, :3]


def _quat(rot: np.ndarray) -> np.ndarray:
    """A rotation matrix's unit quaternion (wxyz)."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rot, np.float64).reshape(9))
    return q


def tool_poses(base: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Tool-tip poses ``[N, 7]`` (xyz, wxyz) in the frame of ``base`` for joints ``q`` ``[N, 6]``."""
    t = base @ dvrk.fk_batch(np.asarray(q, np.float64))
    return np.stack([np.r_[m[:3, 3], _quat(m[:3, :3])] for m in t])
