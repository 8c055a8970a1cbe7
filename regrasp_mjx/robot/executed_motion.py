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

Where a policy's jaws open on the way (issue 67), the trajectory carries the jaw joint
(:class:`~regrasp_mjx.robot.psm_joints.JawTrack`, :func:`~regrasp_mjx.robot.psm_timing.join`): every
piece is tested with the jaws where they are at that moment (the scene's capsules with the jaws turned,
:func:`regrasp_mjx.world.jaw.opened_ends`, not a second scene), and the opening itself, the arm at rest,
by the environment's own proof of the sweep (:func:`regrasp_mjx.world.jaw.sweep_fn`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import mujoco
import numpy as np

from regrasp_mjx.core.config import JAW_MAX_DEG, SceneConfig
from regrasp_mjx.envs.host import quat_conj, quat_from_rotvec, quat_mul, quat_to_rotvec
from regrasp_mjx.envs.lean_checker import LeanChecker
from regrasp_mjx.robot import dvrk, psm_joints
from regrasp_mjx.robot.psm_joints import JAW_MIN_DEG, JawTrack, JointTrajectory
from regrasp_mjx.robot.psm_timing import RATE_HZ, TimedTrajectory, hold, join, time_joints
from regrasp_mjx.world import jaw as jaws
from regrasp_mjx.world.scene import CapsuleFrames, Scene, load_scene

MAX_INSERTIONS = 8
TOOL_REACH = 0.3  # m: farther than any point of the tool's capsules from the RCM (insertion <= 0.24 m)


@dataclasses.dataclass(frozen=True)
class MotionCheck:
    """The executed motion's verdict: ``collides``, the first colliding sample ``index`` and its
    time ``t_s`` (None when clear), ``within_limits`` (every sample's joints within the PSM's
    limits, the jaw's within 0-80 degrees), ``chord_margin_m``, what the test's margin was raised by,
    and ``opening_room_m``, the least room the jaws' opening sweeps keep (None: no opening)."""

    collides: bool
    index: int | None
    t_s: float | None
    within_limits: bool
    chord_margin_m: float
    opening_room_m: float | None = None


def check_motion(timed: TimedTrajectory, base_in_eg, needle_in_eg, policy) -> MotionCheck:
    """Tests the executed motion of ``timed`` (the regrasping PSM whose base frame is ``base_in_eg``,
    4x4 or 7-vector in the grasping end-effector frame e_g) against the needle at ``needle_in_eg``
    (7-vector, e_g) and the grasping tool, with ``policy``'s scene and clearance margin.

    Each piece between two samples is tested along its whole motion (position linear, orientation
    slerped) with the margin raised by how far the forward-kinematics arc can leave that chord over
    one sample period: ``a dt^2 / 8`` for the fastest acceleration ``a`` of any tool point, bounded by
    the joints' accelerations and velocities times :data:`TOOL_REACH`.

    With the jaw joint (``timed.jaw``), each piece is tested with the jaws at that piece's opening,
    and each run of pieces where the jaw turns (the arm at rest there: a piece where both move is
    refused with a ``ValueError``) by the environment's proof that the sweep keeps the clearance margin
    (:func:`opening_room`)."""
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
    within = bool(np.all((timed.q >= dvrk.Q_MIN - 1e-9) & (timed.q <= dvrk.Q_MAX + 1e-9)))
    if timed.jaw is not None:
        return _check_with_jaw(timed, poses, np.asarray(needle_in_eg, np.float64), policy, chord, within)
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
    return MotionCheck(hit is not None, hit, None if hit is None else float(timed.t[hit]), within, chord)


def _check_with_jaw(timed: TimedTrajectory, poses, needle, policy, chord: float, within: bool) -> MotionCheck:
    """:func:`check_motion` of a trajectory with the jaw joint: each piece at its opening, each sweep proved."""
    env = policy.env_config
    scene = load_scene(env.scene)
    deg = np.degrees(timed.jaw)
    within = within and bool(np.all((deg >= JAW_MIN_DEG - 1e-9) & (deg <= JAW_MAX_DEG + 1e-9)))
    turning = deg[1:] != deg[:-1]  # [N - 1]: the pieces where the jaw moves
    if np.any(turning & np.any(timed.q[1:] != timed.q[:-1], axis=1)):
        raise ValueError(
            "a piece where the arm and the jaw both move is not checked: the jaws open with the arm at rest "
            "(psm_timing.join), as the environment proves them clear"
        )
    checkers = {}

    def at(d: float):
        """The checker with the jaws at ``d`` degrees and the needle placed for it (one per opening)."""
        if d not in checkers:
            checker = LeanChecker(at_opening(scene, d), env.clearance_mm + chord * 1e3)
            checkers[d] = (checker, checker.place(needle))
        return checkers[d]

    checker, placed = at(float(deg[0]))
    hit = 0 if checker.pose_collides(placed, *poses[0]) else None
    least, i = None, 1
    while hit is None and i < len(poses):
        if turning[i - 1]:  # a sweep, samples i - 1 to j, the arm at rest
            j = i
            while j + 1 < len(poses) and turning[j]:
                j += 1
            room = opening_room(scene, needle, poses[i - 1], float(deg[i - 1]), float(deg[j]))
            least = room if least is None else min(least, room)
            hit = i if room < env.clearance_mm * 1e-3 else None
            i = j + 1
            continue
        checker, placed = at(float(deg[i]))
        hit = i if checker.motion_collides(placed, poses[i - 1], poses[i]) else None
        i += 1
    return MotionCheck(hit is not None, hit, None if hit is None else float(timed.t[hit]), within, chord, least)


class _Opened(NamedTuple):
    """What :class:`~regrasp_mjx.envs.lean_checker.LeanChecker` reads of a scene, with the jaws elsewhere."""

    config: SceneConfig
    capsule_frames: CapsuleFrames


@functools.lru_cache(maxsize=32)
def at_opening(scene: Scene, deg: float):
    """``scene`` as the lean checker sees it with the regrasping jaws at ``deg`` degrees: its own capsules,
    the jaws turned about the hinge (:func:`regrasp_mjx.world.jaw.opened_ends`, the capsules the scene
    built at that opening has, to 2e-7 m), not a scene built again; the scene itself at its own opening."""
    if abs(deg - scene.config.jaw_angle_deg) < 1e-9:
        return scene
    frames = dataclasses.replace(scene.capsule_frames, tool_ends=jaws.opened_ends(scene, deg))
    return _Opened(dataclasses.replace(scene.config, jaw_angle_deg=float(deg)), frames)


@functools.lru_cache(maxsize=8)
def _sweep_program(scene: Scene):
    """:func:`regrasp_mjx.world.jaw.sweep_fn` of ``scene`` around a needle 7-vector, jitted."""
    others, sweep = scene.motion_distance_fn()[0], jaws.sweep_fn(scene)
    return jax.jit(lambda needle, ee, lo, hi: sweep(others(needle[:3], needle[3:]), ee[:3], ee[3:], lo, hi))


def opening_room(scene: Scene, needle, pose, from_deg: float, to_deg: float) -> float:
    """The room [m] the jaws keep from the needle (7-vector, e_g) and the grasping tool while they turn
    from ``from_deg`` to ``to_deg`` on the tool held at ``pose`` (7-vector): the environment's own proof
    (:func:`regrasp_mjx.world.jaw.sweep_fn`, the least clearance at its check points less how far a
    jaw point moves between them), so an opening the environment made with room is proved here too."""
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    return float(_sweep_program(scene)(f32(needle), f32(pose), np.float32(from_deg), np.float32(to_deg)))


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
    the joint limits, or the motion still collides after :data:`MAX_INSERTIONS` inserted waypoints.
    The jaw's track, where the policy's jaws open, is the plan's (``JointTrajectory.jaw``)."""
    if plan.joints is None:
        raise MotionRefused("the plan has no joints: make it with plan_from_camera(..., psm=...)")
    i = 0 if query is None else query
    joints: JointTrajectory = plan.joints if query is None else plan.joints[query]
    c_eg, c_n = (np.asarray(x, np.float64).reshape(-1, 7) for x in (camera_eg, needle))
    return time_query(policy, joints, bool(np.atleast_1d(plan.success)[i]), c_eg[i], c_n[i], psm, rate_hz)


def time_query(policy, joints: JointTrajectory, success: bool, camera_eg, needle, psm: dict, rate_hz=RATE_HZ):
    """:func:`time_plan` of one query's ``joints`` (with its jaw track) and ``success`` (camera-frame 7-vectors)."""
    if not success:
        raise MotionRefused("the plan did not reach the goal: no motion to time")
    _require_reachable(joints)
    eg_inv = np.linalg.inv(dvrk.as_matrix(camera_eg, "camera_eg"))
    base = eg_inv @ dvrk.as_matrix(psm["regrasping_base"], "psm['regrasping_base']")
    n = eg_inv @ dvrk.as_matrix(needle, "needle")
    return time_waypoints(joints.q, base, np.r_[n[:3, 3], _quat(n[:3, :3])], policy, rate_hz, joints.jaw)


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


def time_executed(
    policy, poses, needle_in_eg, base_in_eg, rate_hz: float = RATE_HZ, jaw: JawTrack | None = None
) -> TimedPlan:
    """The timed, re-checked joint trajectory of a closed loop's executed poses (``execute(...)["poses"]``
    of one row up to its ``steps``: 7-vectors ``[S + 1, 7]`` in e_g) on the regrasping PSM whose base
    is ``base_in_eg``, against the true needle ``needle_in_eg``: the motion the arm makes through the
    steps the loop chose (:func:`time_waypoints`). Raises :class:`MotionRefused` where a pose is
    outside the joint limits or the motion cannot be made clear. ``jaw``: where the jaws open
    (the row's ``opened_at`` and ``jaw_deg``), their track over these poses."""
    joints = psm_joints.joint_trajectory(base_in_eg, poses)
    _require_reachable(joints)
    base = dvrk.as_matrix(base_in_eg, "base_in_eg")
    return time_waypoints(joints.q, base, np.asarray(needle_in_eg, np.float64), policy, rate_hz, jaw)


def time_waypoints(
    waypoints, base_in_eg, needle_in_eg, policy, rate_hz: float = RATE_HZ, jaw: JawTrack | None = None
) -> TimedPlan:
    """:func:`time_joints` of joint ``waypoints`` [W, 6], its motion checked by :func:`check_motion`;
    where it collides or leaves the limits, the Cartesian midpoint of the step around the first bad
    sample is inserted as a waypoint and the whole is timed again (at most :data:`MAX_INSERTIONS`
    times), else :class:`MotionRefused` says where.

    ``jaw`` (required for a policy whose jaws open on the way; a track over the W waypoints): the arm's
    motion to the opening pose and from it, each so timed and repaired with the jaws at their opening,
    joined by the jaw's opening with the arm at rest (:func:`~regrasp_mjx.robot.psm_timing.join`), and
    the whole checked again, the sweep included (:class:`MotionRefused` where it is not proved clear)."""
    waypoints = np.asarray(waypoints, np.float64)
    _check_track(policy, jaw, len(waypoints))
    if jaw is None or not jaw.opens:
        return _repaired(waypoints, base_in_eg, needle_in_eg, policy, rate_hz, None if jaw is None else jaw.from_deg)
    k = jaw.opens_at
    # the sweep first, at the pose the arm rests at (no inserted waypoint can mend it); the whole is checked after
    room = opening_room(
        load_scene(policy.env_config.scene),
        needle_in_eg,
        tool_poses(dvrk.as_matrix(base_in_eg, "base_in_eg"), waypoints[k : k + 1])[0],
        jaw.from_deg,
        jaw.to_deg,
    )
    if room < policy.env_config.clearance_mm * 1e-3:
        raise MotionRefused(_sweep_refusal(jaw, room))
    before = _repaired(waypoints[: k + 1], base_in_eg, needle_in_eg, policy, rate_hz, jaw.from_deg)
    after = _repaired(waypoints[k:], base_in_eg, needle_in_eg, policy, rate_hz, jaw.to_deg)
    timed = join(before.trajectory, after.trajectory, jaw)
    check = check_motion(timed, base_in_eg, needle_in_eg, policy)
    room = check.opening_room_m  # None only where a part collided before the sweep was reached
    if room is not None and room < policy.env_config.clearance_mm * 1e-3:
        raise MotionRefused(_sweep_refusal(jaw, room))
    if check.collides or not check.within_limits:  # each part was clear: only where they join (rounding)
        where = f"collides at {check.t_s:.3f} s" if check.collides else "leaves the joint limits"
        raise MotionRefused(f"the arm's motion with the jaws' opening {where}; the plan is refused")
    return TimedPlan(timed, check, before.inserted + after.inserted)


def _sweep_refusal(jaw: JawTrack, room: float) -> str:
    """Why a plan whose jaws' opening is not proved clear is refused."""
    return (
        f"the jaws' opening at pose {jaw.opens_at} ({jaw.from_deg:g} to {jaw.to_deg:g} deg, the arm at rest) is not "
        f"proved clear of the needle and the grasping tool (room {1e3 * room:.3f} mm); the plan is refused"
    )


def _check_track(policy, jaw: JawTrack | None, poses: int) -> None:
    """A ``ValueError`` where a jaw track is missing (a policy whose jaws open on the way), of another
    length than the waypoints, or starting elsewhere than the policy's scene's opening."""
    env = policy.env_config
    if jaw is None:
        if env.jaw_open_deg is not None:
            raise ValueError(
                f"jaw=None is not accepted for a policy whose jaws open on the way (to {env.jaw_open_deg:g} deg): "
                "its JawTrack.of(policy.env_config, opens_at, poses), opens_at from jaw_opening.opening_steps or "
                "execute(...)['opened_at']"
            )
        return
    if not isinstance(jaw, JawTrack):
        raise ValueError(f"jaw={jaw!r} is not accepted: a psm_joints.JawTrack or None")
    if jaw.poses != poses:
        raise ValueError(f"jaw.poses={jaw.poses} is not accepted: the track of these {poses} waypoints")
    if abs(jaw.from_deg - env.scene.jaw_angle_deg) > 1e-9:
        raise ValueError(
            f"jaw.from_deg={jaw.from_deg:g} is not accepted: the policy's scene's opening, "
            f"{env.scene.jaw_angle_deg:g} deg, where every plan starts"
        )


def _repaired(waypoints, base_in_eg, needle_in_eg, policy, rate_hz: float, jaw_deg: float | None) -> TimedPlan:
    """:func:`time_waypoints`' loop: timed, checked with the jaws held at ``jaw_deg`` (None: the
    scene's, no jaw joint), a waypoint inserted where it collides or leaves the limits."""
    waypoints = np.asarray(waypoints, np.float64).copy()
    for inserted in range(MAX_INSERTIONS + 1):
        timed = time_joints(waypoints, rate_hz)
        if jaw_deg is not None:
            timed = hold(timed, jaw_deg)
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
