"""A plan as motion a dVRK PSM follows: a time-optimal joint trajectory through its waypoints at
the arm's own velocity and acceleration limits, sampled at the controller's rate, and that motion
re-checked against the needle and the other tool.

The PSM's controller streams joint positions (``servo_jp``) at its rate, and a remote-centre arm's
tool tip does not move on the checked Cartesian step when its joints are interpolated, so the
executed motion is checked where it goes, not where the plan's steps went:

- :func:`time_joints` fits one C2 spline through the waypoints in joint space (knots spaced by the
  time each segment needs at the velocity limits) and times it with TOPP-RA (the time-optimal
  parameterisation of a given path under joint velocity and acceleration limits, Pham and Pham
  2018), compiled in :mod:`regrasp_mjx.robot.topp` (the ``toppra`` library's results in a tenth of
  its time; ``engine="toppra"`` uses the library). TOPP-RA, not Ruckig: the motion must pass through every waypoint of a
  checked plan, and Ruckig's community edition plans to one target state (its waypoints are a
  paid feature); the path is fixed first and only its timing is optimised, which is what the re-check
  needs.
- :func:`check_motion` poses the tool by forward kinematics at every sample and tests each 1-ms piece
  with the lean collision test along its whole motion (:class:`~regrasp_mjx.envs.lean_checker.LeanChecker`),
  the margin raised by how far the arc of forward kinematics can leave the piece's chord.
- :func:`time_plan` does both for a plan from ``Policy.plan_from_camera(..., psm=...)``; where a
  piece collides it inserts the Cartesian midpoint of the step around it as a waypoint (its joints by
  inverse kinematics, nearest the previous ones) and times again, at most :data:`MAX_INSERTIONS`
  times, and otherwise refuses the plan with the time and step that collide: never a silent
  collision.

Limits (:data:`V_MAX`, :data:`A_MAX`): the dVRK's own for the PSM's joint trajectories,
``jhu-dvrk/sawIntuitiveResearchKit`` ``core/components/code/mtsIntuitiveResearchKitPSM.cpp``
(commit 9e535e6, 2026-04-17, lines 726-731): 90 deg/s and 90 deg/s^2 for the outer yaw and pitch,
0.2 m/s and 0.2 m/s^2 for the insertion, 1080 deg/s and 720 deg/s^2 for the roll and the wrist.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import mujoco
import numpy as np
import toppra
import toppra.algorithm
import toppra.constraint
import toppra.solverwrapper

from regrasp_mjx.envs.host import quat_conj, quat_from_rotvec, quat_mul, quat_to_rotvec
from regrasp_mjx.envs.lean_checker import LeanChecker
from regrasp_mjx.robot import dvrk, psm_joints, topp
from regrasp_mjx.robot.psm_joints import JointTrajectory
from regrasp_mjx.world.scene import load_scene

V_MAX = np.array([math.pi / 2, math.pi / 2, 0.2, 6 * math.pi, 6 * math.pi, 6 * math.pi])  # rad/s, m/s
A_MAX = np.array([math.pi / 2, math.pi / 2, 0.2, 4 * math.pi, 4 * math.pi, 4 * math.pi])  # rad/s^2, m/s^2
RATE_HZ = 1000.0  # the dVRK's servo rate
MAX_INSERTIONS = 8
# TOPP-RA's grid along the path: every waypoint (a knot of the spline) and this many points inside
# each segment between two, Chebyshev-spaced (densest next to the knots, where the spline's curvature,
# and with it how fast the joints move for a path velocity, changes most). Against a uniform grid of
# max(200, 40 W) points: about 5x fewer points, the motion a few percent longer (experiments/RESULTS.md,
# issue 48: TOPP-RA's time grows with its points, its motion shrinks with them)
GRID_PER_SEGMENT = 8
MAX_RESCALES = 4  # uniform slow-downs of a timing whose samples pass a limit (one is the rule)
# the share of each limit TOPP-RA is given: all of it, since the motion between its grid points is
# slowed to the limits afterwards (path_ratio); below 1 it leaves room and motion time
HEADROOM = 1.0
ENGINES = ("compiled", "toppra")  # time_joints' TOPP-RA: regrasp_mjx.robot.topp, or the toppra library
TOOL_REACH = 0.3  # m: farther than any point of the tool's capsules from the RCM (insertion <= 0.24 m)


@dataclasses.dataclass(frozen=True)
class TimedTrajectory:
    """Joint positions ``q``, velocities ``qd`` and accelerations ``qdd`` ``[N, 6]`` at times ``t``
    ``[N]`` (s, from 0, at ``rate_hz``; the last sample is the end), through ``waypoints`` ``[W, 6]``."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    waypoints: np.ndarray
    rate_hz: float

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])


def time_joints(
    waypoints,
    rate_hz: float = RATE_HZ,
    v_max=V_MAX,
    a_max=A_MAX,
    gridpoints: int | None = None,
    engine: str = "compiled",
) -> TimedTrajectory:
    """The time-optimal trajectory through joint ``waypoints`` ``[W, 6]`` (at rest at both ends) under
    ``v_max`` and ``a_max`` (6 each), sampled at ``rate_hz`` (see the module's docstring): TOPP-RA's
    timing (:func:`raw_timing`, at :data:`HEADROOM` of the limits) slowed uniformly by the largest
    excess anywhere between its grid points (:func:`path_ratio`), so that every sample keeps the
    limits. ``gridpoints``: TOPP-RA's grid along the path, that many points spaced evenly (default:
    the knots and :data:`GRID_PER_SEGMENT` points between two, :func:`knot_grid`; a coarser grid is
    faster to compute and gives longer motion, experiments/RESULTS.md). ``engine``: ``"compiled"``
    (:mod:`regrasp_mjx.robot.topp`, toppra's algorithm and results in about a tenth of its time) or
    ``"toppra"`` (the library itself, the reference)."""
    if engine not in ENGINES:
        raise ValueError(f"engine={engine!r} is not accepted: one of {', '.join(map(repr, ENGINES))}")
    q = np.asarray(waypoints, np.float64)
    if q.ndim != 2 or q.shape[1] != 6 or len(q) < 1 or not np.all(np.isfinite(q)):
        raise ValueError(f"waypoints of shape {q.shape} are not accepted: [W, 6] finite joint vectors, W >= 1")
    v_max, a_max = np.asarray(v_max, np.float64), np.asarray(a_max, np.float64)
    if v_max.shape != (6,) or a_max.shape != (6,) or np.any(~(v_max > 0)) or np.any(~(a_max > 0)):
        raise ValueError("v_max and a_max are not accepted: 6 positive numbers each")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz={rate_hz!r} is not accepted: a positive number (the controller's rate)")
    # knots spaced by the time each segment takes at the velocity limits; a repeated waypoint is dropped
    span = np.max(np.abs(np.diff(q, axis=0)) / v_max, axis=1) if len(q) > 1 else np.zeros(0)
    keep = np.r_[True, span > 1e-12]
    q, span = q[keep], span[keep[1:]]
    if len(q) == 1:
        zero = np.zeros((1, 6))
        return TimedTrajectory(np.zeros(1), q.copy(), zero, zero.copy(), q.copy(), float(rate_hz))
    if gridpoints is not None and not (isinstance(gridpoints, int) and gridpoints >= 2):
        raise ValueError(f"gridpoints={gridpoints!r} is not accepted: an integer >= 2")
    path, grid, sd = raw_timing(q, gridpoints, v_max, a_max, engine)
    # TOPP-RA holds the limits at its grid points; between them the motion can pass one (the path's
    # curvature changes within an interval): the whole motion is slowed uniformly by the largest
    # excess anywhere along it (velocities / r, accelerations / r^2), then sampled
    sd = sd / max(1.0, path_ratio(path, grid, sd, v_max, a_max))
    for _ in range(MAX_RESCALES):
        t, position, velocity, acceleration = sample_const_accel(path, grid, sd, rate_hz)
        over = limit_ratio(velocity, acceleration, v_max, a_max)
        if over <= 1.0:
            return TimedTrajectory(t, position, velocity, acceleration, q, float(rate_hz))
        sd = sd / (over * (1.0 + 1e-3))  # a sample past path_ratio's points (rare): slowed again
    raise ValueError(f"no timing within the limits after {MAX_RESCALES} uniform slow-downs (last excess {over:.6f})")


def raw_timing(q: np.ndarray, gridpoints: int | None = None, v_max=V_MAX, a_max=A_MAX, engine: str = "compiled"):
    """TOPP-RA's own timing of distinct waypoints ``q`` ``[W >= 2, 6]``: ``(path, gridpoints, sd)``,
    the C2 spline through them (knots spaced by the time each segment takes at the velocity limits)
    and the path velocities at the grid's points, at :data:`HEADROOM` of the limits; ``gridpoints``
    None: :func:`knot_grid`, else that many points spaced evenly; ``engine`` as :func:`time_joints`."""
    v_max, a_max = np.asarray(v_max, np.float64), np.asarray(a_max, np.float64)
    span = np.max(np.abs(np.diff(q, axis=0)) / v_max, axis=1)
    ss = np.r_[0.0, np.cumsum(span)]
    ss /= ss[-1]
    grid = np.linspace(0.0, 1.0, gridpoints) if gridpoints else knot_grid(ss)
    path = topp.Spline(ss, q)
    if engine == "toppra":  # the library's spline (scipy's, the same to 1e-15) and passes
        reference = toppra.SplineInterpolator(ss, q, bc_type="clamped" if len(q) > 2 else "natural")
        solver = toppra.algorithm.TOPPRA(
            _constraints(tuple(v_max * HEADROOM), tuple(a_max * HEADROOM)),
            reference,
            gridpoints=grid,
            solver_wrapper="seidel",
        )
        solver.compute_parameterization(0.0, 0.0)
        ok = solver.problem_data.return_code == toppra.algorithm.ParameterizationReturnCode.Ok
        sd = solver.problem_data.sd_vec if ok else None
    else:
        sd = topp.path_velocities(path(grid, 1), path(grid, 2), grid, v_max * HEADROOM, a_max * HEADROOM)
    if sd is not None and np.all(np.isfinite(sd)) and len(grid) > 2 and np.all(sd[1:-1] > 0):
        return path, grid, sd  # (2 points at rest: no motion at all)
    raise ValueError("TOPP-RA found no trajectory through these waypoints at these limits")


def knot_grid(knots: np.ndarray, per_segment: int = GRID_PER_SEGMENT) -> np.ndarray:
    """The path's grid: the spline's ``knots`` (increasing, 0 to 1) and ``per_segment`` points inside
    each segment at the Chebyshev points' spacing, ``(1 - cos(pi k / (n + 1))) / 2``."""
    inner = (1.0 - np.cos(np.pi * np.arange(1, per_segment + 1) / (per_segment + 1))) / 2.0
    knots = np.asarray(knots, np.float64)
    points = knots[:-1, None] + inner[None, :] * np.diff(knots)[:, None]
    return np.sort(np.r_[knots, points.ravel()])


def path_ratio(path, gridpoints: np.ndarray, sd: np.ndarray, v_max, a_max, points: int = 2000) -> float:
    """:func:`limit_ratio` of the motion TOPP-RA's ``sd`` makes (the path acceleration constant between
    grid points, :func:`sample_const_accel`) at both ends of every grid interval and points inside
    it, about ``points`` in all (at least 2 inside each), where the samples at the controller's rate
    fall anywhere (a coarse grid's intervals need the most: its curvature changes within them);
    ``path`` a :class:`~regrasp_mjx.robot.topp.Spline` (compiled, :func:`~regrasp_mjx.robot.topp.motion_ratio`)."""
    ss, sd = np.asarray(gridpoints, np.float64), np.asarray(sd, np.float64)
    v_max, a_max = np.asarray(v_max, np.float64), np.asarray(a_max, np.float64)
    return topp.motion_ratio(path.knots, path.coef, ss, sd, max(2, points // len(ss)), v_max, a_max)


def limit_ratio(qd: np.ndarray, qdd: np.ndarray, v_max=V_MAX, a_max=A_MAX) -> float:
    """The uniform slow-down ``r`` (time x r) that brings samples ``qd``, ``qdd`` ``[N, 6]`` within the
    limits: ``max(|qd| / v_max, sqrt(|qdd| / a_max))`` over every sample and joint (<= 1: within)."""
    v = float(np.max(np.abs(qd) / v_max)) if len(qd) else 0.0
    a = float(np.max(np.abs(qdd) / a_max)) if len(qdd) else 0.0
    return max(v, math.sqrt(a))


def _available_solvers(output_msg: bool = True, _found=toppra.solverwrapper.available_solvers(output_msg=False)):
    """``toppra.solverwrapper.available_solvers`` looked up once: toppra's every TOPPRA() searches
    sys.path for its optional solvers (0.1 ms of a plan's timing, profiled), which cannot appear
    while a process runs."""
    if output_msg:
        print(_found)
    return _found


toppra.solverwrapper.available_solvers = _available_solvers


@functools.lru_cache(maxsize=8)
def _constraints(v: tuple[float, ...], a: tuple[float, ...]) -> list:
    """TOPP-RA's joint velocity and acceleration constraints, made once per limits: toppra formats
    every limit into a string as it makes a constraint (0.4 ms of a plan's 1.5 ms, profiled)."""
    v, a = np.asarray(v), np.asarray(a)
    return [
        toppra.constraint.JointVelocityConstraint(np.stack([-v, v], 1)),
        toppra.constraint.JointAccelerationConstraint(np.stack([-a, a], 1)),
    ]


def sample_const_accel(path, gridpoints: np.ndarray, sd: np.ndarray, rate_hz: float):
    """Times and joint positions, velocities and accelerations at ``rate_hz`` along ``path`` (a
    :class:`~regrasp_mjx.robot.topp.Spline`) timed by TOPP-RA's path velocities ``sd`` at
    ``gridpoints``, the path acceleration constant between grid points:
    ``toppra.parametrizer.ParametrizeConstAccel``'s trajectory, compiled (:func:`~regrasp_mjx.robot.topp.sample`;
    toppra's own loop over samples took two thirds of a plan's timing, experiments/RESULTS.md)."""
    ss, sd = np.asarray(gridpoints, np.float64), np.asarray(sd, np.float64)
    return topp.sample(path.knots, path.coef, ss, sd, float(rate_hz))


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
    t = base @ dvrk._fk_batch(np.asarray(q, np.float64), np)
    return np.stack([np.r_[m[:3, 3], _quat(m[:3, :3])] for m in t])
